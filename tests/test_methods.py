"""The method vocabulary shared by eval/robot.py and eval/imagenet.py (eval/common/methods.py)."""
from pathlib import Path

import pytest
import torch

import tts
from common.methods import IMAGE_KINDS, ROBOT_KINDS, install, parse_method


@pytest.mark.parametrize("spec, label, slug", [
    ("dense", "dense", "dense"),
    ("ddim:7", "ddim:7", "ddim-7"),
    ("uniform:0.93:timestep", "uniform:0.93:timestep", "uniform-0.93-timestep"),
    ("every_n:5:rollout", "every_n:5:rollout", "every_n-5-rollout"),
    ("rotating:0.93:rollout", "rotating:0.93:rollout", "rotating-0.93-rollout"),
    ("file:results/schedules/lift_steps_0.93.json", "file:lift_steps_0.93", "file-lift_steps_0.93"),
    ("file:results/schedules/lift_steps_0.93.json+taylor1", "file:lift_steps_0.93+taylor1",
     "file-lift_steps_0.93+taylor1"),
    ("pruner:checkpoints/pruners/lift_tts_0.93@0.93", "pruner:lift_tts_0.93@0.93", "pruner-lift_tts_0.93-at0.93"),
    ("pruner:checkpoints/pruners/lift_tts_0.93", "pruner:lift_tts_0.93", "pruner-lift_tts_0.93"),
    ("taylorseer:5:2", "taylorseer:5:2", "taylorseer-5-2"),
    ("toca:6@0.8", "toca:6@0.8", "toca-6-at0.8"),
    ("diffusers:fbc@0.8", "diffusers:fbc@0.8", "diffusers-fbc-at0.8"),
])
def test_labels_name_rows_by_what_they_are(spec, label, slug):
    m = parse_method(spec)
    assert (m.label, m.slug) == (label, slug)


def test_parsed_fields():
    m = parse_method("pruner:a/b/p@0.9", forecast=2)
    assert (m.kind, m.path, m.sparsity, m.forecast, m.engine) == ("pruner", Path("a/b/p"), 0.9, 2, True)
    assert parse_method("ddim:3").n == 3 and not parse_method("ddim:3").engine
    d = parse_method("diffusers:taylorseer:5:2")
    assert (d.cache, d.n, d.order, d.engine) == ("taylorseer", 5, 2, False)
    assert parse_method("uniform:0.5:forward").direction == "forward"
    ddpm = parse_method("ddpm:7", kinds=ROBOT_KINDS)  # the policy's own stochastic sampler on 7 steps
    assert (ddpm.kind, ddpm.n, ddpm.sampler.scheduler, ddpm.sampler.spacing, ddpm.engine) == ("ddpm", 7, "ddpm", None, False)


@pytest.mark.parametrize("spec, kinds, message", [
    ("bogus", IMAGE_KINDS, "unknown method 'bogus'; the vocabulary is dense"),
    ("uniform:0.93", IMAGE_KINDS, "malformed method"),
    ("uniform:1.0:timestep", IMAGE_KINDS, r"sparsity must be in \[0, 1\)"),
    ("uniform:0.9:sideways", IMAGE_KINDS, "unknown direction 'sideways'"),
    ("every_n:0:timestep", IMAGE_KINDS, "interval must be >= 1"),
    ("rotating:0.9:forward", ROBOT_KINDS, "moves whole steps"),
    ("ddim:x", IMAGE_KINDS, "number of steps must be an integer"),
    ("ddim:0", IMAGE_KINDS, "at least 1 step"),
    ("pruner:p@1.2", IMAGE_KINDS, r"after '@' must be in \[0, 1\)"),
    ("pruner:", IMAGE_KINDS, "malformed"),
    ("uniform:0.9:timestep@0.9", IMAGE_KINDS, "budget applies to"),
    ("toca:6", IMAGE_KINDS, "exactly one of a fresh-token ratio"),
    ("toca:6:0.2", ROBOT_KINDS, "not available in this suite"),
    ("ddpm:7", IMAGE_KINDS, "not available in this suite"),
    ("ddpm:7:trailing", ROBOT_KINDS, "a sampler is ddim:K"),
    ("diffusers:fbc", IMAGE_KINDS, "exactly one of a threshold"),
])
def test_bad_specs_say_what_is_wrong(spec, kinds, message):
    with pytest.raises(ValueError, match=message):
        parse_method(spec, kinds=kinds)


def test_forecast_only_for_timestep_reuse():
    with pytest.raises(ValueError, match="applies to timestep reuse of file:"):
        parse_method("toca:6@0.8", forecast=1)
    with pytest.raises(ValueError, match="timestep reuse only"):
        parse_method("uniform:0.9:rollout+taylor1")
    assert parse_method("uniform:0.93:timestep+taylor1").label == "uniform:0.93:timestep+taylor1"
    with pytest.raises(ValueError, match="disagree"):
        parse_method("file:x.json+taylor2", forecast=1)


def test_install_builds_the_plan_the_spec_names(tmp_path):
    layer = torch.nn.TransformerEncoderLayer(16, 2, 32, dropout=0.0, batch_first=True)
    model = torch.nn.TransformerEncoder(layer, 3, enable_nested_tensor=False).eval()
    x = torch.randn(2, 5, 16)
    with install(model, parse_method("every_n:3:timestep")) as acc:
        assert isinstance(acc.plan, tts.plans.IntervalPlan) and acc.plan.n == 3
        assert acc.directions == ("timestep",)
    ref = model(x)
    with install(model, parse_method("dense")) as acc:
        assert acc.plan.describe() == "dense"
        acc.new_call()
        assert torch.equal(model(x), ref)
    import json

    (tmp_path / "s.json").write_text(json.dumps({"directions": ["timestep"], "grid": [[0] * 6, [2] * 6]}))
    with install(model, parse_method(f"file:{tmp_path / 's.json'}")) as acc:
        assert acc.plan.decisions.shape == (1, 2, 6) and acc.directions == ("timestep",)
    with install(model, parse_method("rotating:0.5:timestep")) as acc:
        assert isinstance(acc.plan, tts.plans.RotatingPlan) and acc.plan.sparsity == 0.5
    with pytest.raises(FileNotFoundError, match="no schedule at"):
        install(model, parse_method(f"file:{tmp_path / 'missing.json'}"))
    with pytest.raises(ValueError, match="does not run in the tts engine"):
        install(model, parse_method("ddim:4"))


def test_result_files_of_other_policies_never_collide_with_the_bundled_ones():
    from common import policy_slug

    assert policy_slug("lift") == "lift"
    assert policy_slug("lift", Path("checkpoints/lift_dpt")) == "lift"
    assert policy_slug("lift", Path("checkpoints/lift_mh_dpt")) == "lift-lift_mh_dpt"
