"""The reference implementation's pruner recipe as options: sizes, zero head bias, linear decay, no clipping."""
import pytest
import torch

import tts
from test_pruner import _toy_policy_and_trajectories
from tts.policy_training import PolicyPrunerTrainingConfig, build_policy_pruner, train_policy_pruner
from tts.trajectories import load_trajectories
from tts.training import lr_factor


def test_reference_recipe_fields(tmp_path):
    c = PolicyPrunerTrainingConfig.reference(tmp_path / "p", directions="timestep,rollout")
    assert (c.hidden, c.heads, c.ffn, c.lr, c.weight_decay, c.batch, c.epochs) == (512, 8, 1024, 1e-4, 1e-4, 16, 20)
    assert c.lr_schedule == "linear" and c.clip_grad is None and not c.paired
    assert c.head_bias == [0.0, 0.0, 0.0]  # compute + two directions, no preference
    assert PolicyPrunerTrainingConfig.reference(tmp_path / "p", epochs=3).epochs == 3
    with pytest.raises(ValueError, match="lr_schedule"):
        PolicyPrunerTrainingConfig(out=tmp_path / "p", lr_schedule="step")
    with pytest.raises(ValueError, match="clip_grad"):
        PolicyPrunerTrainingConfig(out=tmp_path / "p", clip_grad=0.0)


def test_linear_schedule_warms_up_then_decays_to_zero():
    f = [lr_factor(e, 20, "linear") for e in range(20)]
    assert f[0] == pytest.approx(0.25) and f[3] == pytest.approx(1.0 - 3 / 20)  # 4 warm-up epochs
    assert all(a > b for a, b in zip(f[3:], f[4:])) and f[-1] == pytest.approx(1 / 20)
    c = [lr_factor(e, 20, "cosine") for e in range(20)]
    assert c[10] == pytest.approx(0.5) and f[10] == pytest.approx(0.5)


def test_reference_sized_pruner_has_the_recipes_layers(tmp_path, one_thread):
    pol = _toy_policy_and_trajectories(tmp_path, [3, 4])
    pruner = build_policy_pruner(pol, PolicyPrunerTrainingConfig.reference(tmp_path / "p"))
    assert (pruner.config.hidden, pruner.config.heads, pruner.config.ffn) == (512, 8, 1024)
    head = [m for m in pruner.modules() if isinstance(m, torch.nn.Linear)][-1]
    assert head.out_features == 4 and torch.equal(head.bias, torch.zeros(4))  # zero head bias


def test_without_clipping_large_gradients_reach_the_optimizer(tmp_path, one_thread, monkeypatch):
    pol = _toy_policy_and_trajectories(tmp_path, [3, 3, 4])
    episodes, _ = load_trajectories(tmp_path / "traj.pt")
    calls = []
    real = torch.nn.utils.clip_grad_norm_
    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", lambda *a, **k: calls.append(1) or real(*a, **k))
    base = dict(sparsity=0.6, epochs=1, batch=2, n_train=2, n_val=1, hidden=8, heads=2, ffn=16, log=None)
    for clip, expected in ((1.0, True), (None, False)):
        calls.clear()
        out = tmp_path / f"p{clip}"
        kw = {k: v for k, v in base.items() if k != "log"}
        train_policy_pruner(pol, episodes, PolicyPrunerTrainingConfig(out=out, clip_grad=clip, run_dir=out, **kw),
                            log=None)
        assert bool(calls) == expected
        assert tts.load_pruner(out).metadata["clip_grad"] == clip


def test_cli_recipe_reference_sets_the_defaults_and_explicit_options_win(tmp_path, one_thread):
    import train_pruner

    _toy_policy_and_trajectories(tmp_path, [3, 3, 4])
    out = tmp_path / "ref"
    train_pruner.main(["--trajectories", str(tmp_path / "traj.pt"), "--checkpoint", str(tmp_path / "policy"),
                       "--out", str(out), "--recipe", "reference", "--epochs", "1", "--batch", "2", "--n-train", "2",
                       "--n-val", "1", "--directions", "timestep,rollout", "--run-dir", str(tmp_path / "run")])
    meta = tts.load_pruner(out).metadata
    assert (meta["hidden"], meta["heads"], meta["ffn"], meta["lr"], meta["lr_schedule"]) == (512, 8, 1024, 1e-4, "linear")
    assert meta["clip_grad"] is None and meta["paired"] is False and meta["epochs"] == 1 and meta["batch"] == 2
    assert [float(b) for b in meta["head_bias"].split(",")] == [0.0, 0.0, 0.0] and meta["recipe"] == "reference"


def test_recipes_keep_training_state_where_git_tracks_it():
    """A new checkout has no ignored files: every recipe training resumes from ``state_dir`` (a
    tracked folder, committed at a stop), and ``.gitignore`` does not hide that folder."""
    import re
    import shutil
    import subprocess
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    run_dirs = []
    for recipe in sorted((repo / "recipes").glob("*.sh")):
        text = recipe.read_text()
        for line in text.splitlines():
            if re.search(r"python eval/train_(policy|pruner|image_pruner)\.py", line) and "--export" not in line:
                call = text[text.index(line):].split(";", 1)[0]  # the command up to its first ';'
                assert "--run-dir \"$(state_dir" in call, f"{recipe.name}: a training without state_dir: {line.strip()}"
        run_dirs += re.findall(r"--run-dir \S+", text)
    assert run_dirs and all("state_dir" in r for r in run_dirs), run_dirs
    lib = (repo / "recipes" / "lib.sh").read_text()
    folder = re.search(r'state_dir\(\) \{ echo "([^"$]+)/\$1"; \}', lib).group(1)
    if shutil.which("git") and (repo / ".git").exists():
        ignored = subprocess.run(["git", "check-ignore", "-q", f"{folder}/some_training/state.pt"], cwd=repo)
        assert ignored.returncode == 1, f"{folder} is ignored by .gitignore: its state would not survive a new checkout"
