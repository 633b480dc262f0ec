"""diffusers' own caches as image baselines: official -> diffusers DiT conversion, per-call cache state,
executed-branch and MAC counts, removal, eval/imagenet.py argument checks."""
from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import torch

pytest.importorskip("timm")
pytest.importorskip("diffusers")

from conftest import randomize, tiny_official_dit  # noqa: E402
from tts.adapters.dit import sample_dit  # noqa: E402
from image_suite.diffusers_cache import DiffusersCache, calibrate_fbc_threshold  # noqa: E402
from tts.adapters.dit_diffusers import (DiffusersDiT,  # noqa: E402
                                        to_diffusers)

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")

STEPS = 12
DEPTH = 3  # tiny_official_dit


def _setup(seed: int = 0):
    model = randomize(tiny_official_dit(), seed=seed, std=0.05).eval()
    labels = torch.tensor([1, 7, 3])
    noise = torch.randn(3, 4, 8, 8, generator=torch.Generator().manual_seed(seed))
    return model, labels, noise


def test_converted_model_computes_the_official_function():
    model, labels, noise = _setup()
    tr = to_diffusers(model)
    x = torch.randn(4, 4, 8, 8)
    t = torch.tensor([999, 400, 13, 0])
    y = torch.tensor([0, 5, 9, 10])  # 10: the null class
    with torch.no_grad():
        ref = model(x, t, y)
        out = tr(x, timestep=t, class_labels=y, return_dict=False)[0]
    assert out.shape == ref.shape
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    # the diffusers default timestep features (downscale_freq_shift=1) would not match
    tr.transformer_blocks[0].norm1.emb.time_proj.downscale_freq_shift = 1
    with torch.no_grad():
        off = tr(x, timestep=t, class_labels=y, return_dict=False)[0]
    assert (off - ref).abs().max() > 1e-4
    wrapped = DiffusersDiT.from_dit(model)
    torch.testing.assert_close(sample_dit(wrapped, labels, steps=STEPS, noise=noise),
                               sample_dit(model, labels, steps=STEPS, noise=noise), atol=1e-5, rtol=1e-5)


def test_taylorseer_computes_steps_0_2_7_and_resets_between_calls():
    model, labels, noise = _setup()
    wrapped = DiffusersDiT.from_dit(model)
    dense = sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    cache = DiffusersCache(wrapped, "taylorseer", interval=5, order=2, warmup=1)
    first = sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    call = cache.last_call()
    # warm-up step 0, then (step - 2) % 5 == 0: steps 0, 2, 7 compute both branches of every block
    assert call.forwards == STEPS and call.computed == 3 * 2 * DEPTH
    assert call.sparsity(DEPTH) == pytest.approx(1 - 3 / STEPS)
    assert call.macs < call.macs_dense() * 0.5  # skipped branches ran no Linear
    assert not torch.allclose(first, dense, atol=1e-4)
    second = sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    assert torch.equal(first, second)  # state reset at the start of each sampling call
    assert len(cache.calls) == 2 and cache.calls[1].computed == call.computed
    cache.remove()
    torch.testing.assert_close(sample_dit(wrapped, labels, steps=STEPS, noise=noise), dense, atol=0, rtol=0)


def test_first_block_cache_threshold_zero_is_dense_and_huge_threshold_runs_only_block_0():
    model, labels, noise = _setup()
    wrapped = DiffusersDiT.from_dit(model)
    dense = sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    cache = DiffusersCache(wrapped, "fbc", threshold=0.0)
    out = sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    call = cache.last_call()
    assert call.computed == 2 * DEPTH * STEPS and call.sparsity(DEPTH) == 0.0
    assert call.macs == pytest.approx(call.macs_dense())
    torch.testing.assert_close(out, dense, atol=1e-6, rtol=1e-6)
    cache.remove()
    cache = DiffusersCache(wrapped, "fbc", threshold=1e9)
    sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    call = cache.last_call()
    # step 0 computes every block; afterwards only the first block (both of its branches)
    assert call.computed == 2 * DEPTH + 2 * (STEPS - 1)
    assert cache.describe() == "diffusers FirstBlockCache(threshold=1e+09)"
    cache.remove()


def test_calibrated_threshold_reproduces_its_sparsity_and_bad_input_errors():
    model, labels, noise = _setup()
    wrapped = DiffusersDiT.from_dit(model)
    threshold, reached = calibrate_fbc_threshold(wrapped, 0.5, labels, noise, steps=STEPS, iters=6)
    cache = DiffusersCache(wrapped, "fbc", threshold=threshold)
    sample_dit(wrapped, labels, steps=STEPS, noise=noise)
    assert cache.last_call().sparsity(DEPTH) == pytest.approx(reached)
    assert reached <= (DEPTH - 1) / DEPTH
    cache.remove()
    with pytest.raises(ValueError, match="unknown diffusers cache"):
        DiffusersCache(wrapped, "magcache")
    with pytest.raises(ValueError, match="warmup >= 1"):
        DiffusersCache(wrapped, "taylorseer", warmup=0)
    with pytest.raises(TypeError, match="DiffusersDiT"):
        DiffusersCache(model, "fbc")
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        calibrate_fbc_threshold(wrapped, 1.0, labels, noise)


def test_imagenet_cli_checks_the_diffusers_cache_arguments():
    import imagenet
    from common.methods import parse_method

    def args(**kw):
        base = dict(num_samples=4, batch=2, steps=4, out=Path("x.npz"), seed=0, calib_seed=1)
        base.update(kw)
        return argparse.Namespace(**base)

    with pytest.raises(ValueError, match="exactly one of a threshold"):
        parse_method("diffusers:fbc")
    with pytest.raises(ValueError, match="exactly one of a threshold"):
        parse_method("diffusers:fbc:0.1@0.8")
    with pytest.raises(ValueError, match="--calib-seed must differ"):
        imagenet.check_args(args(calib_seed=0), parse_method("diffusers:fbc@0.8"))
    with pytest.raises(ValueError, match="budget applies to"):
        parse_method("every_n:5:timestep@0.8")
    with pytest.raises(ValueError, match="malformed"):
        parse_method("diffusers:taylorseer:5:2@0.8")
    imagenet.check_args(args(calib_seed=0), parse_method("diffusers:fbc:0.1"))  # a threshold needs no calibration


def _pipeline_folder(tmp_path, model):
    """A DiTPipeline-style folder (model_index.json + transformer/) holding ``model`` converted, with
    diffusers' own timestep features (what a downloaded diffusers DiT computes). diffusers does not
    save the fixed sin-cos position embedding (it recomputes it), so the randomised one is reset."""
    from tts.adapters.dit import sincos_pos_embed_2d

    d, grid = model.pos_embed.shape[-1], model.config.input_size // model.config.patch_size
    model.pos_embed.data.copy_(sincos_pos_embed_2d(d, grid)[None])
    tr = to_diffusers(model)
    for block in tr.transformer_blocks:
        block.norm1.emb.time_proj.downscale_freq_shift = 1
    tr.save_pretrained(tmp_path / "pipe" / "transformer")
    (tmp_path / "pipe" / "model_index.json").write_text('{"_class_name": "DiTPipeline"}')
    return tmp_path / "pipe", tr


def test_diffusers_folder_loads_samples_and_accelerates(tmp_path):
    import tts
    from tts.adapters.dit import load_dit

    model, labels, noise = _setup()
    folder, tr = _pipeline_folder(tmp_path, model)
    loaded = load_dit(folder)
    assert isinstance(loaded, DiffusersDiT) and loaded.vae_path is None
    assert loaded.config == model.config
    assert load_dit(folder / "transformer").config == model.config
    ref = sample_dit(DiffusersDiT(tr.eval(), model.config), labels, steps=STEPS, noise=noise)
    dense = sample_dit(loaded, labels, steps=STEPS, noise=noise)
    torch.testing.assert_close(dense, ref, atol=1e-6, rtol=1e-6)
    with tts.accelerate(loaded, ("forward", "timestep")) as acc:  # the dense plan: the model's own forward
        assert torch.equal(sample_dit(loaded, labels, steps=STEPS, noise=noise), dense)
        assert acc.target.condition is not None  # a pruner reads block 0's condition memory
    with tts.accelerate(loaded, ("timestep",), plan=tts.plans.every_n(3, "timestep")) as acc:
        sample_dit(loaded, labels, steps=STEPS, noise=noise)
        call = acc.summary().calls[-1]
        assert call.decisions().shape == (STEPS, 2 * len(labels), 2 * DEPTH)  # CFG rows [cond; uncond]
        assert acc.summary().sparsity_of(call) == pytest.approx(1 - 4 / STEPS)
    with pytest.raises(FileNotFoundError, match="DiTPipeline folder"):
        load_dit(tmp_path)


def test_imagenet_script_samples_a_diffusers_folder_with_a_diffusers_cache(tmp_path):
    import json

    import numpy as np

    from tts.adapters.dit import DiT, DiTConfig

    import imagenet

    pixel = randomize(DiT(DiTConfig(input_size=8, patch_size=2, in_channels=3, hidden_size=32, depth=2, num_heads=2,
                                    num_classes=10, learn_sigma=False)), std=0.05).eval()
    folder, _ = _pipeline_folder(tmp_path, pixel)
    out = tmp_path / "s.npz"
    res = imagenet.main(["--model", str(folder), "--method", "diffusers:taylorseer:2:1", "--num-samples", "4",
                         "--batch", "2", "--steps", "6", "--out", str(out),
                         "--no-progress"])
    arr = np.load(out)["arr_0"]
    assert arr.shape == (4, 8, 8, 3) and arr.dtype == np.uint8
    # full steps 0, 2, 4 of 6 (warm-up 1, then every 2nd from step 2)
    assert res["sparsity"] == pytest.approx(0.5) and res["macs_ratio"] > 1.2
    assert json.loads(out.with_suffix(".json").read_text())["plan"].startswith("diffusers TaylorSeer(interval=2")
    latent, _, _ = _setup()
    folder, _ = _pipeline_folder(tmp_path / "latent", latent)
    with pytest.raises(ValueError, match="latent DiT"):  # 4 channels and no vae/ in the folder
        imagenet.main(["--model", str(folder), "--num-samples", "2", "--steps", "2", "--out", str(out)])
