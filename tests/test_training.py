"""Pruner training as library code: the config object, the policy trainer, the resumable loop."""
import json
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import tts
from test_pruner import _toy_policy_and_trajectories
from test_robot_pipeline import obs_batch
from tts.plans import COMPUTE, ROLLOUT, TIMESTEP
from tts.policy_training import PolicyPrunerTrainingConfig, train_policy_pruner
from tts.pruner import Pruner, PrunerConfig
from tts.trajectories import load_trajectories
from tts.io import device_name
from tts.training import PrunerTrainingConfig, TrainingStopped, fit, read_grid

REPO = Path(__file__).resolve().parents[1]


def _decisions(policy, pruner):
    """Decisions [K, B, nb] and actions of the second call of an episode (the first is dense)."""
    with tts.accelerate(policy, pruner.config.directions, pruner=pruner, parallel=False) as acc:
        policy.predict_action(obs_batch(3, 0), torch.Generator().manual_seed(0))
        out = policy.predict_action(obs_batch(3, 1), torch.Generator().manual_seed(1))["action_pred"]
        return acc.summary().calls[-1].decisions(), out


def test_train_policy_pruner_from_a_config_object_round_trips_through_the_checkpoint(tmp_path):
    pol = _toy_policy_and_trajectories(tmp_path, [3 + e % 2 for e in range(6)])
    episodes, _ = load_trajectories(tmp_path / "traj.pt")
    config = PolicyPrunerTrainingConfig(out=tmp_path / "pruner_0.6", sparsity=0.6, epochs=2, batch=2, n_train=4,
                                        n_val=2, lr=0.02, hidden=16, paired=True, run_dir=tmp_path / "run")
    pruner = train_policy_pruner(pol, episodes, config, metadata={"note": "from python"}, log=None)
    back = tts.load_pruner(config.out)
    for (k, a), b in zip(pruner.state_dict().items(), back.state_dict().values()):
        assert torch.equal(a, b), k  # the returned pruner is the best epoch's, as written
    d_trained, a_trained = _decisions(pol, pruner)
    d_loaded, a_loaded = _decisions(pol, back)
    assert torch.equal(d_trained, d_loaded) and torch.equal(a_trained, a_loaded)
    assert (d_loaded != COMPUTE).any()  # it learned to reuse (the head starts biased to compute)
    meta = back.metadata
    assert meta == pruner.metadata and meta["note"] == "from python"
    assert meta["n_train_episodes"] == 4 and meta["n_val_episodes"] == 2 and len(meta["history"]) == 2
    assert meta["best_epoch"] in meta["history"] and meta["pruner_macs_per_call"] > 0
    for row in meta["history"]:  # validation splits the reuse decisions by direction
        shares = [row[f"val_reuse_{d}"] for d in ("forward", "timestep", "rollout")]
        assert min(shares) >= 0 and sum(shares) == pytest.approx(row["val_sparsity"], abs=1e-6)
    assert max(meta["history"][-1][f"val_reuse_{d}"] for d in ("forward", "timestep", "rollout")) > 0
    # the checkpoint records the options it was trained with: the same config comes back from it
    assert PolicyPrunerTrainingConfig.from_dict(meta) == config
    assert meta["directions"] == ["forward", "timestep", "rollout"] and meta["out"] == str(config.out)


def test_validation_floor_is_the_val_l1_of_a_pruner_that_computes_everything(tmp_path):
    """The checkpoint records the untouched policy's val L1 under the validation's own noise draws: a
    pruner that never reuses (compute forced by its head bias, learning rate 0) scores exactly that,
    and it is above zero because the target was drawn with other noise."""
    pol = _toy_policy_and_trajectories(tmp_path, [3 + e % 2 for e in range(6)])
    episodes, _ = load_trajectories(tmp_path / "traj.pt")
    config = PolicyPrunerTrainingConfig(out=tmp_path / "never_reuses", sparsity=0.6, epochs=1, batch=2, n_train=4,
                                        n_val=2, lr=0.0, weight_decay=0.0, hidden=16, head_bias=[1e4, 0, 0, 0],
                                        run_dir=tmp_path / "run")
    meta = train_policy_pruner(pol, episodes, config, log=None).metadata
    (row,) = meta["history"]
    assert row["val_sparsity"] == 0.0
    assert meta["val_l1_dense"] == pytest.approx(row["val_l1"], rel=1e-6) and meta["val_l1_dense"] > 0


# ---------------------------------------------------------------- the loop: resume and mismatches
class Interrupted(Exception):
    pass


def _toy_run(config, interrupt_at=None, trained=None, hidden=8, interrupt_at_group=None, stop_at_group=None,
             clock=None):
    """fit() on a small pruner whose epochs use the shuffle rng, the noise generator and dropout (the
    global generator), i.e. every random state an exact resume must restore. ``clock``: a one-item
    list that each trained group advances by 100 (seconds of a fake clock)."""
    torch.manual_seed(0)
    pruner = Pruner(PrunerConfig(memory_dim=8, num_branches=3, directions=("timestep",), hidden=hidden, heads=2,
                                 ffn=16, dropout=0.2))
    memory = torch.randn(16, 4, 2, 8, generator=torch.Generator().manual_seed(1))

    def train_epoch(opt, rng, noise_rng, epoch, progress):
        if epoch == interrupt_at:
            raise Interrupted
        rows = list(progress.rows)
        for g, idx in enumerate(np.array_split(rng.permutation(16), 4)):
            if g < progress.skip:
                continue
            if (epoch, g) == interrupt_at_group:
                raise Interrupted
            if trained is not None:
                trained.append((epoch, g))
            if clock is not None:
                clock[0] += 100.0
            noisy = memory[idx] + 0.1 * torch.randn(len(idx), 4, 2, 8, generator=noise_rng)
            loss = (pruner(noisy).softmax(-1)[..., 0] - 0.3).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            rows.append({"l1": float(loss.detach()), "sparsity": 0.5, "frames": len(idx)})
            if (epoch, g) == stop_at_group:  # a stop requested while this group trained
                config.stop_path.touch()
            progress.done(rows)
        return rows

    def validate():
        with torch.no_grad():
            p = pruner.eval()(memory).softmax(-1)[..., 0]
        return [{"l1": float((p - 0.3).abs().mean()), "sparsity": float(1 - p.mean()), "frames": 16}]

    best = fit(pruner, config, train_epoch=train_epoch, validate=validate, steps=4, memory_tokens=2, log=None)
    return pruner, best


def test_resume_after_an_interrupted_epoch_continues_from_the_saved_state(tmp_path):
    def config(name, **kw):
        return PrunerTrainingConfig(out=tmp_path / name, run_dir=tmp_path / f"run_{name}", directions="timestep",
                                    sparsity=0.5, epochs=3, lr=0.05, **kw)

    _toy_run(config("whole"))
    with pytest.raises(Interrupted):
        _toy_run(config("cut"), interrupt_at=2)  # epochs 1 and 2 done and saved, the third interrupted
    assert len(tts.load_pruner(tmp_path / "cut").metadata["history"]) == 2
    trained = []
    _toy_run(config("cut", resume=True), trained=trained)
    assert trained == [(2, g) for g in range(4)]  # only the missing epoch ran
    whole, cut = (torch.load(tmp_path / f"run_{n}" / "pruner_state.pt", weights_only=False) for n in ("whole", "cut"))
    for k, a in whole["pruner"].items():  # the same shuffles, noise and dropout as the uninterrupted run
        assert torch.equal(a, cut["pruner"][k]), k
    assert [h["val_score"] for h in whole["history"]] == [h["val_score"] for h in cut["history"]]
    assert [h["epoch"] for h in tts.load_pruner(tmp_path / "cut").metadata["history"]] == [1, 2, 3]
    # resuming a finished run trains nothing
    trained.clear()
    _toy_run(config("cut", resume=True), trained=trained)
    assert trained == []
    # a state that does not belong to this run is refused, not half-loaded
    with pytest.raises(ValueError, match="different pruner.*hidden"):
        _toy_run(config("cut", resume=True), hidden=16)
    with pytest.raises(ValueError, match="other lr"):
        _toy_run(replace(config("cut", resume=True), lr=0.01))


def test_resume_inside_an_epoch_skips_the_trained_groups_and_matches_an_uninterrupted_run(tmp_path, monkeypatch):
    def config(name, **kw):
        return PrunerTrainingConfig(out=tmp_path / name, run_dir=tmp_path / f"run_{name}", directions="timestep",
                                    sparsity=0.5, epochs=3, lr=0.05, **kw)

    clock = [0.0]
    monkeypatch.setattr(tts.training, "time", SimpleNamespace(time=lambda: clock[0]))
    _toy_run(config("whole"), clock=clock)
    with pytest.raises(Interrupted):  # epoch 1 done; epoch 2 interrupted after two of its four groups
        _toy_run(config("cut"), interrupt_at_group=(1, 2), clock=clock)
    state = torch.load(tmp_path / "run_cut" / "pruner_state.pt", weights_only=False)
    assert state["epoch"] == 1 and state["partial"]["groups"] == 2
    trained = []
    _toy_run(config("cut", resume=True), trained=trained, clock=clock)
    assert trained == [(1, 2), (1, 3)] + [(2, g) for g in range(4)]
    whole, cut = (torch.load(tmp_path / f"run_{n}" / "pruner_state.pt", weights_only=False) for n in ("whole", "cut"))
    for k, a in whole["pruner"].items():  # the same shuffles, noise and dropout as the uninterrupted run
        assert torch.equal(a, cut["pruner"][k]), k
    assert [h["val_score"] for h in whole["history"]] == [h["val_score"] for h in cut["history"]]
    assert [h["train_l1"] for h in whole["history"]] == [h["train_l1"] for h in cut["history"]]
    assert cut["partial"] is None
    # the training time counts the groups trained before the interruption too, as a whole run's does
    assert cut["history"][-1]["train_seconds"] == whole["history"][-1]["train_seconds"] == 1200
    assert cut["precision_log"] == [{"epoch": 0, "groups": 0, "precision": "float32", "device": device_name("cpu")}]


def test_a_requested_stop_ends_the_run_at_its_next_save_and_the_resume_matches_an_uninterrupted_run(tmp_path):
    def config(name, **kw):
        return PrunerTrainingConfig(out=tmp_path / name, run_dir=tmp_path / f"run_{name}", directions="timestep",
                                    sparsity=0.5, epochs=3, lr=0.05, **kw)

    _toy_run(config("whole"))
    cut = config("cut")
    assert cut.stop_path == tmp_path / "run_cut" / "STOP"
    trained = []
    with pytest.raises(TrainingStopped, match=r"in epoch 2 of 3 after 2 groups.*resume"):
        _toy_run(cut, trained=trained, stop_at_group=(1, 1))
    assert trained[-1] == (1, 1) and not cut.stop_path.exists()  # the request is used up
    state = torch.load(cut.state_path, weights_only=False)
    assert state["epoch"] == 1 and state["partial"]["groups"] == 2  # the group in progress was saved first
    trained.clear()
    _toy_run(config("cut", resume=True), trained=trained)
    assert trained == [(1, 2), (1, 3)] + [(2, g) for g in range(4)]
    whole, done = (torch.load(tmp_path / f"run_{n}" / "pruner_state.pt", weights_only=False) for n in ("whole", "cut"))
    for k, a in whole["pruner"].items():
        assert torch.equal(a, done["pruner"][k]), k
    assert [h["val_score"] for h in whole["history"]] == [h["val_score"] for h in done["history"]]


def test_a_stop_request_left_before_the_run_starts_is_removed_not_obeyed(tmp_path):
    config = PrunerTrainingConfig(out=tmp_path / "p", run_dir=tmp_path / "run", directions="timestep",
                                  sparsity=0.5, epochs=2, lr=0.05)
    config.stop_path.parent.mkdir(parents=True)
    config.stop_path.touch()
    _toy_run(config)  # trains both epochs
    assert not config.stop_path.exists()
    assert [h["epoch"] for h in tts.load_pruner(tmp_path / "p").metadata["history"]] == [1, 2]


def test_a_trainer_stopped_on_request_exits_with_its_own_status():
    sys.path.insert(0, str(REPO / "eval"))
    from common.training_args import STOPPED_STATUS, exit_when_stopped

    def stopped():
        raise TrainingStopped("stopped in epoch 1 of 2 after 1 groups")

    with pytest.raises(SystemExit) as e:
        exit_when_stopped(stopped)
    assert e.value.code == STOPPED_STATUS != 0
    assert exit_when_stopped(lambda: 7) == 7


def test_a_resume_may_change_the_precision_and_the_change_is_recorded(tmp_path):
    """A run moved to a machine without fast bfloat16 continues in float32 (or the reverse); the state and
    the checkpoint say from which epoch and group each precision ran."""
    def config(**kw):
        return PrunerTrainingConfig(out=tmp_path / "p", run_dir=tmp_path / "run", directions="timestep",
                                    sparsity=0.5, epochs=3, lr=0.05, precision="bfloat16", **kw)

    with pytest.raises(Interrupted):  # epoch 1 done; epoch 2 interrupted after two of its four groups
        _toy_run(config(), interrupt_at_group=(1, 2))
    trained = []
    _toy_run(replace(config(resume=True), precision="float32"), trained=trained)
    assert trained == [(1, 2), (1, 3)] + [(2, g) for g in range(4)]
    cpu = device_name("cpu")
    log = [{"epoch": 0, "groups": 0, "precision": "bfloat16", "device": cpu},
           {"epoch": 1, "groups": 2, "precision": "float32", "device": cpu}]
    assert torch.load(tmp_path / "run" / "pruner_state.pt", weights_only=False)["precision_log"] == log
    assert tts.load_pruner(tmp_path / "p").metadata["precision_log"] == log
    _toy_run(replace(config(resume=True), precision="float32"))  # finished: no further stretch
    assert tts.load_pruner(tmp_path / "p").metadata["precision_log"] == log


def test_a_resume_on_another_device_starts_a_new_stretch(tmp_path):
    """A training begun on a GPU and continued on a CPU says which groups ran where; a state saved
    before devices were recorded is not split by the device alone."""
    config = PrunerTrainingConfig(out=tmp_path / "p", run_dir=tmp_path / "run", directions="timestep",
                                  sparsity=0.5, epochs=3, lr=0.05)
    with pytest.raises(Interrupted):
        _toy_run(config, interrupt_at_group=(1, 2))
    path = tmp_path / "run" / "pruner_state.pt"
    state = torch.load(path, weights_only=False)
    state["precision_log"][0]["device"] = "cuda: NVIDIA H200"  # as a GPU run would have saved it
    torch.save(state, path)
    _toy_run(replace(config, resume=True))
    assert torch.load(path, weights_only=False)["precision_log"] == [
        {"epoch": 0, "groups": 0, "precision": "float32", "device": "cuda: NVIDIA H200"},
        {"epoch": 1, "groups": 2, "precision": "float32", "device": device_name("cpu")}]
    with pytest.raises(Interrupted):
        _toy_run(replace(config, run_dir=tmp_path / "old"), interrupt_at_group=(1, 2))
    old = tmp_path / "old" / "pruner_state.pt"
    state = torch.load(old, weights_only=False)
    del state["precision_log"][0]["device"]
    torch.save(state, old)
    _toy_run(replace(config, run_dir=tmp_path / "old", resume=True))
    assert torch.load(old, weights_only=False)["precision_log"] == [{"epoch": 0, "groups": 0, "precision": "float32"}]


# ---------------------------------------------------------------- config and grids
def test_config_validates_and_reads_options_from_a_mapping(tmp_path):
    with pytest.raises(ValueError, match="epochs"):
        PrunerTrainingConfig(out=tmp_path / "p", epochs=0)
    with pytest.raises(ValueError, match="unknown direction"):
        PrunerTrainingConfig(out=tmp_path / "p", directions="forward,sideways")
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        PrunerTrainingConfig(out=tmp_path / "p", sparsity=1.0)
    with pytest.raises(ValueError, match="val_mode"):
        PrunerTrainingConfig(out=tmp_path / "p", val_mode="top")
    with pytest.raises(ValueError, match="needs tie_branches"):
        PrunerTrainingConfig(out=tmp_path / "p", step_query=True)
    with pytest.raises(ValueError, match="static"):
        PolicyPrunerTrainingConfig(out=tmp_path / "p", static=True, prior="every_n:2")
    c = PolicyPrunerTrainingConfig.from_dict({"out": str(tmp_path / "p"), "directions": "rollout,timestep",
                                              "head_bias": "2,0,1", "threads": 1, "checkpoint": "x"})
    assert c.directions == ("timestep", "rollout") and c.head_bias == [2.0, 0.0, 1.0] and c.out == tmp_path / "p"
    assert c.state_path == Path("runs") / "p" / "pruner_state.pt"


def test_cli_rejects_options_that_do_not_combine():
    import train_pruner

    with pytest.raises(SystemExit):
        train_pruner.main(["--trajectories", "t.pt", "--checkpoint", "c", "--out", "o", "--static",
                           "--prior", "s.json"])


def test_read_grid_from_a_file_strings_or_a_tensor(tmp_path):
    rows = ["CCC", "TRT", "TCT"]
    (tmp_path / "s.json").write_text(json.dumps({"grid": rows}))
    g = read_grid(tmp_path / "s.json")
    assert g.tolist() == [[COMPUTE] * 3, [TIMESTEP, ROLLOUT, TIMESTEP], [TIMESTEP, COMPUTE, TIMESTEP]]
    assert torch.equal(read_grid(rows), g) and torch.equal(read_grid(str(tmp_path / "s.json")), g)
    assert torch.equal(read_grid(g), g)
    assert read_grid(rows, reuse="rollout")[1].tolist() == [ROLLOUT] * 3
    with pytest.raises(ValueError, match="steps, branches"):
        read_grid(torch.zeros(3, dtype=torch.int8))
    # a tensor prior is recorded in the checkpoint as strings, which read back as the same grid
    cfg = PrunerTrainingConfig(out=tmp_path / "p", prior=g)
    assert cfg.to_json()["prior"] == rows and torch.equal(read_grid(cfg.to_json()["prior"]), g)


def test_committed_pruner_checkpoints_still_load():
    """Every committed pruner loads. A training in progress is committed as its checkpoint JSON
    alone (the history so far, a progress record); its weights come with the finished training."""
    from tts.training import training_finished

    paths = sorted((REPO / "checkpoints" / "pruners").glob("*.json"))
    if not paths:
        pytest.skip("no committed pruner checkpoints")
    for path in paths:
        if not path.with_suffix(".safetensors").exists():
            assert not training_finished(path), f"{path.name}: a finished training without its weights"
            continue
        pruner = tts.load_pruner(path)
        assert "history" in pruner.metadata, path.name
