"""eval/sample_spread.py: the spread / same-draw / other-draw arithmetic, and a run on a toy policy."""
import json

import pytest
import torch

from sample_spread import spread_stats


def test_collapsing_two_modes_to_their_mean_lowers_the_unpaired_l1_and_the_spread():
    # the dense policy: mode +1 on draw 0, mode -1 on draw 1 of each of 3 calls; its recorded action is +1
    target = torch.ones(3, 2)
    dense = torch.stack([torch.ones(3, 2), -torch.ones(3, 2)])
    r = spread_stats(dense, target)
    assert r == {"spread": 1.0, "l1_same_draw": 0.0, "l1_other_draw": 2.0, "calls": 3, "draws": 2}
    # a method that returns the mean of the modes whatever the noise: no spread, yet a lower unpaired L1
    mean = spread_stats(torch.zeros(2, 3, 2), target)
    assert mean["spread"] == 0.0 and mean["l1_other_draw"] == 1.0 < r["l1_other_draw"]
    assert mean["l1_same_draw"] == 1.0 > r["l1_same_draw"]
    with pytest.raises(ValueError, match="same calls"):
        spread_stats(dense, target[:2])
    with pytest.raises(ValueError, match="D >= 2"):
        spread_stats(dense[:1], target)


def test_dense_replays_its_recorded_actions_and_other_draws_differ(tmp_path, one_thread):
    import sample_spread
    from test_pruner import _toy_policy_and_trajectories

    _toy_policy_and_trajectories(tmp_path, [3, 4, 3])
    out = tmp_path / "spread.json"
    res = sample_spread.main(["--task", "lift", "--checkpoint", str(tmp_path / "policy"), "--trajectories",
                              str(tmp_path / "traj.pt"), "--first-episode", "0", "--draws", "3", "--batch", "2",
                              "--methods", "dense", "ddim:2", "--out", str(out)])
    dense, ddim = res["methods"]["dense"], res["methods"]["ddim:2"]
    assert dense["calls"] == 2 + 3 + 2  # every call but each episode's first
    assert dense["l1_same_draw"] < 1e-5  # the recorded noise gives back the recorded action
    assert dense["l1_other_draw"] > 0.01 and dense["spread"] > 0.01
    assert ddim["l1_same_draw"] > 1e-3  # another sampler on the same noise is not the dense action
    assert json.loads(out.read_text())["methods"].keys() == {"dense", "ddim:2"}
    args = ["--task", "lift", "--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
            "--first-episode", "0", "--out", str(out), "--resume"]
    again = sample_spread.main(args + ["--draws", "3", "--methods", "dense", "dpm:2"])  # dense kept, dpm:2 added
    assert again["methods"]["dense"] == dense and again["methods"].keys() == {"dense", "ddim:2", "dpm:2"}
    other = sample_spread.main(args + ["--draws", "2", "--methods", "dense"])
    assert other["methods"].keys() == {"dense"} and other["methods"]["dense"]["draws"] == 2  # other draws: anew
    with pytest.raises(SystemExit):
        sample_spread.main(["--task", "lift", "--checkpoint", str(tmp_path / "policy"), "--trajectories",
                            str(tmp_path / "traj.pt"), "--methods", "dense", "--draws", "1"])


def test_a_fewer_step_sampler_leaves_the_policy_on_its_own_sampler(tmp_path, one_thread):
    from common.methods import ROBOT_KINDS, parse_method
    from sample_spread import sample_draws
    from test_pruner import _toy_policy_and_trajectories
    from tts.trajectories import load_trajectories

    pol = _toy_policy_and_trajectories(tmp_path, [3, 3])
    episodes, _ = load_trajectories(tmp_path / "traj.pt")
    draws, target = sample_draws(pol, parse_method("ddim:2", kinds=ROBOT_KINDS), episodes, 2, 2)
    assert draws.shape == (2, 4, *target.shape[1:]) and target.shape[0] == 4
    assert (pol.cfg.scheduler, pol.cfg.num_inference_steps) == ("ddpm", 6)


def test_resume_measures_a_pruner_again_when_its_weights_changed(tmp_path, one_thread):
    """A training in progress rewrites its checkpoint under the same name: a kept entry counts only for
    the weights it was measured with."""
    import shutil

    import sample_spread
    import train_pruner
    from test_pruner import _toy_policy_and_trajectories

    _toy_policy_and_trajectories(tmp_path, [3, 4, 3, 3, 4, 3])
    common = ["--trajectories", str(tmp_path / "traj.pt"), "--checkpoint", str(tmp_path / "policy"), "--sparsity",
              "0.5", "--epochs", "1", "--batch", "2", "--n-train", "4", "--n-val", "2", "--hidden", "16"]
    for seed in (0, 1):
        train_pruner.main(common + ["--out", str(tmp_path / f"pruner_{seed}"), "--seed", str(seed)])
    live = tmp_path / "live" / "pruner"
    live.parent.mkdir()

    def publish(seed):  # the training's checkpoint, rewritten in place
        for ext in (".json", ".safetensors"):
            shutil.copy(tmp_path / f"pruner_{seed}{ext}", live.with_suffix(ext))

    args = ["--task", "lift", "--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
            "--first-episode", "4", "--draws", "2", "--batch", "2", "--methods", f"pruner:{live}",
            "--out", str(tmp_path / "spread.json"), "--resume"]
    publish(0)
    first = sample_spread.main(args)["methods"][f"pruner:{live.name}"]
    assert len(first["weights_sha256"]) == 64
    assert sample_spread.main(args)["methods"][f"pruner:{live.name}"] == first  # same weights: kept
    publish(1)
    second = sample_spread.main(args)["methods"][f"pruner:{live.name}"]
    assert second["weights_sha256"] != first["weights_sha256"]
    assert second["l1_same_draw"] != first["l1_same_draw"]  # measured again, with the other weights
