"""eval/train_policy.py: a tiny run on a hand-made robomimic file, checked through load_policy."""
import json

import numpy as np
import pytest
import torch

pytest.importorskip("h5py")

from robot_suite.robomimic import Demo, write_demos  # noqa: E402
from robot_suite.tasks import OBS_KEYS  # noqa: E402

DIMS = {"object": 10, "robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}


def test_dropout_reaches_every_residual_branch_of_the_trained_policy(tmp_path, one_thread):
    import train_policy
    from tts.adapters.dp_policy import load_policy

    rng = np.random.default_rng(0)
    demos = [Demo(obs={k: rng.normal(size=(n, DIMS[k])) for k in OBS_KEYS}, actions=rng.uniform(-1, 1, (n, 7)),
                  rewards=np.arange(n) == n - 1, dones=np.arange(n) == n - 1) for n in (24, 30)]
    write_demos(tmp_path / "d.hdf5", demos, {"env_name": "Lift"})
    out = tmp_path / "policy"
    train_policy.main(["--data", str(tmp_path / "d.hdf5"), "--out", str(out), "--steps", "3", "--batch", "4",
                       "--width", "16", "--layers", "2", "--heads", "2", "--dropout", "0.3",
                       "--run-dir", str(tmp_path / "run")])
    policy = load_policy(out)
    assert policy.model.config.p_drop_attn == 0.3
    layers = policy.model.decoder.layers
    # self-attention, cross-attention and MLP outputs each pass a dropout of p = 0.3 before the residual add
    assert all(getattr(layer, f"dropout{i}").p == 0.3 for layer in layers for i in (1, 2, 3))
    assert all(layer.self_attn.dropout == 0.3 for layer in layers)
    policy.model.eval()
    assert not any(m.training for m in policy.model.modules())  # loaded for inference: dropout off
    note = json.loads((tmp_path / "policy.json").read_text())["metadata"]["note"]
    assert "single scripted expert" in note  # no quality masks: one demonstrator


def test_a_run_shorter_than_its_warm_up_trains(tmp_path, one_thread):
    """--steps below 10 still trains: the warm-up is at least one step."""
    import train_policy
    from tts.adapters.dp_policy import load_policy

    rng = np.random.default_rng(1)
    demos = [Demo(obs={k: rng.normal(size=(20, DIMS[k])) for k in OBS_KEYS}, actions=rng.uniform(-1, 1, (20, 7)),
                  rewards=np.arange(20) == 19, dones=np.arange(20) == 19)]
    write_demos(tmp_path / "d.hdf5", demos, {"env_name": "Lift"})
    args = ["--data", str(tmp_path / "d.hdf5"), "--width", "16", "--layers", "1", "--heads", "2", "--batch", "4"]
    train_policy.main(args + ["--out", str(tmp_path / "a"), "--steps", "2", "--run-dir", str(tmp_path / "ra")])
    train_policy.main(args + ["--out", str(tmp_path / "b"), "--steps", "4", "--run-dir", str(tmp_path / "rb")])
    a, b = load_policy(tmp_path / "a").model.state_dict(), load_policy(tmp_path / "b").model.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)  # the two extra steps changed the weights
    if not torch.cuda.is_available():  # a GPU that is not there is an error, not a silent CPU run
        with pytest.raises(SystemExit, match="no such CUDA device"):
            train_policy.main(args + ["--out", str(tmp_path / "c"), "--steps", "2", "--device", "cuda:0"])


def test_push_t_data_trains_on_its_own_observation_keys(tmp_path, one_thread):
    import train_policy
    from tts.adapters.dp_policy import load_policy
    from robot_suite.tasks import TASKS, env_args

    rng = np.random.default_rng(2)
    keys = TASKS["pusht"].obs_keys
    dims = {"agent_pos": 2, "block_keypoints": 16}
    demos = [Demo(obs={k: rng.normal(size=(20, dims[k])) for k in keys}, actions=rng.uniform(0, 512, (20, 2)),
                  rewards=np.arange(20) == 19, dones=np.arange(20) == 19)]
    write_demos(tmp_path / "d.hdf5", demos, env_args("pusht"), masks={"better": ["demo_0"], "okay": [], "worse": []})
    train_policy.main(["--data", str(tmp_path / "d.hdf5"), "--out", str(tmp_path / "p"), "--steps", "2",
                       "--width", "16", "--layers", "1", "--heads", "2", "--batch", "4", "--run-dir", str(tmp_path / "r")])
    policy = load_policy(tmp_path / "p")
    assert list(policy.cfg.obs_keys) == list(keys) and list(policy.cfg.obs_dims) == [2, 16]
    assert policy.cfg.action_dim == 2
    note = json.loads((tmp_path / "p.json").read_text())["metadata"]["note"]
    assert "mixed quality" in note and "single" not in note  # robomimic's MH quality masks: several operators


def test_warm_start_copies_weights_and_refuses_another_architecture(tmp_path, one_thread):
    import train_policy
    from tts.adapters.dp_policy import load_policy

    rng = np.random.default_rng(3)
    demos = [Demo(obs={k: rng.normal(size=(20, DIMS[k])) for k in OBS_KEYS}, actions=rng.uniform(-1, 1, (20, 7)),
                  rewards=np.arange(20) == 19, dones=np.arange(20) == 19)]
    write_demos(tmp_path / "d.hdf5", demos, {"env_name": "Lift"})
    base = ["--data", str(tmp_path / "d.hdf5"), "--heads", "2", "--batch", "4"]
    train_policy.main(base + ["--width", "16", "--layers", "1", "--out", str(tmp_path / "a"), "--steps", "2",
                              "--run-dir", str(tmp_path / "ra")])
    train_policy.main(base + ["--width", "16", "--layers", "1", "--out", str(tmp_path / "b"), "--steps", "1",
                              "--lr", "0", "--init", str(tmp_path / "a"), "--run-dir", str(tmp_path / "rb")])
    a, b = load_policy(tmp_path / "a").state_dict(), load_policy(tmp_path / "b").state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)  # lr 0: the warm start is the starting checkpoint
    # another dropout rate is not another architecture: the continued policy keeps the weights, trains
    # (and records) its own rate
    train_policy.main(base + ["--width", "16", "--layers", "1", "--out", str(tmp_path / "d"), "--steps", "1",
                              "--lr", "0", "--dropout", "0.3", "--init", str(tmp_path / "a"), "--run-dir", str(tmp_path / "rd")])
    d = load_policy(tmp_path / "d")
    assert all(torch.equal(a[k], d.state_dict()[k]) for k in a) and d.cfg.model["p_drop_attn"] == 0.3
    with pytest.raises(SystemExit, match="differ"):
        train_policy.main(base + ["--width", "32", "--layers", "1", "--out", str(tmp_path / "c"), "--steps", "1",
                                  "--init", str(tmp_path / "a"), "--run-dir", str(tmp_path / "rc")])


def test_resumed_policy_training_continues_the_saved_optimiser_ema_and_losses(tmp_path, one_thread):
    """--resume restores the saved step, EMA step, optimiser and loss history (eval/common/model_training)
    and trains only the steps that are left."""
    import train_policy

    rng = np.random.default_rng(4)
    demos = [Demo(obs={k: rng.normal(size=(20, DIMS[k])) for k in OBS_KEYS}, actions=rng.uniform(-1, 1, (20, 7)),
                  rewards=np.arange(20) == 19, dones=np.arange(20) == 19)]
    write_demos(tmp_path / "d.hdf5", demos, {"env_name": "Lift"})
    base = ["--data", str(tmp_path / "d.hdf5"), "--heads", "2", "--batch", "4", "--width", "16", "--layers", "1",
            "--out", str(tmp_path / "p"), "--run-dir", str(tmp_path / "r"), "--save-every", "1"]
    train_policy.main(base + ["--steps", "2"])
    first = torch.load(tmp_path / "r" / "state.pt", weights_only=False)
    train_policy.main(base + ["--steps", "4", "--resume"])
    st = torch.load(tmp_path / "r" / "state.pt", weights_only=False)
    assert (st["step"], st["ema_step"], len(st["losses"])) == (4, 4, 4)
    assert st["losses"][:2] == first["losses"]  # the history continues, not restarts
    assert {float(v["step"]) for v in st["opt"]["state"].values()} == {4.0}  # AdamW's own count carried over


def test_an_interrupted_dit_training_resumes_to_the_same_weights(tmp_path, one_thread):
    """eval/train_dit.py saves data and torch RNG states with the model, EMA and optimiser: stopping at
    step 2 and resuming gives exactly the weights of an uninterrupted run."""
    pytest.importorskip("sklearn")
    import train_dit
    from tts.adapters.dit import load_dit

    base = ["--steps", "4", "--batch", "4", "--size", "8", "--hidden", "16", "--depth", "1", "--heads", "2",
            "--warmup", "1", "--save-every", "1"]
    train_dit.main(base + ["--out", str(tmp_path / "a"), "--run-dir", str(tmp_path / "ra")])
    train_dit.main(base + ["--out", str(tmp_path / "b"), "--run-dir", str(tmp_path / "rb"), "--stop-at", "2"])
    assert not (tmp_path / "b.json").exists()
    train_dit.main(base + ["--out", str(tmp_path / "b"), "--run-dir", str(tmp_path / "rb"), "--resume"])
    a, b = load_dit(tmp_path / "a").state_dict(), load_dit(tmp_path / "b").state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_window_indices_pad_the_edges_across_demos():
    import train_policy

    idx = train_policy.window_indices([3, 2], horizon=4, n_obs=2, n_act=2)
    # demo 0 (frames 0-2): starts -1, 0; demo 1 (frames 3-4): start -1 only
    assert idx.tolist() == [[0, 0, 1, 2], [0, 1, 2, 2], [3, 3, 4, 4]]


def test_image_policy_trains_encoder_and_transformer_from_an_image_dataset(tmp_path, one_thread):
    """--obs-type image: camera frames and proprioception (no object state) condition the policy; the
    encoder's weights train with the transformer; the checkpoint loads as the image policy."""
    import train_policy
    from tts.adapters.dp_image_policy import DiffusionTransformerHybridImagePolicy
    from tts.adapters.dp_policy import load_policy

    rng = np.random.default_rng(3)
    cams = ("agentview_image", "robot0_eye_in_hand_image")
    demos = [Demo(obs={**{k: rng.normal(size=(n, DIMS[k])) for k in OBS_KEYS},
                       **{c: rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8) for c in cams}},
                  actions=rng.uniform(-1, 1, (n, 7)), rewards=np.arange(n) == n - 1, dones=np.arange(n) == n - 1)
             for n in (12, 14)]
    write_demos(tmp_path / "img.hdf5", demos, {"env_name": "Lift"})
    args = ["--data", str(tmp_path / "img.hdf5"), "--obs-type", "image", "--encoder-width", "16", "--crop", "12",
            "--width", "16", "--layers", "1", "--heads", "2", "--batch", "4"]
    train_policy.main(args + ["--out", str(tmp_path / "a"), "--steps", "2", "--run-dir", str(tmp_path / "ra")])
    train_policy.main(args + ["--out", str(tmp_path / "b"), "--steps", "4", "--run-dir", str(tmp_path / "rb")])
    a, b = load_policy(tmp_path / "a"), load_policy(tmp_path / "b")
    assert isinstance(a, DiffusionTransformerHybridImagePolicy) and list(a.cfg.obs_keys) == list(train_policy.PROPRIO_KEYS)
    assert a.image_cfg.crop_size == 12 and a.image_cfg.image_size == 16 and a.image_cfg.width == 16
    ea, eb = a.obs_encoder.state_dict(), b.obs_encoder.state_dict()
    assert any(not torch.equal(ea[k], eb[k]) for k in ea)  # the encoder trained
    obs = {k: torch.as_tensor(demos[0].obs[k][None, :2]).float() for k in train_policy.PROPRIO_KEYS}
    obs.update({c: demos[0].obs[c][None, :2] for c in cams})
    out = a.predict_action(obs, torch.Generator().manual_seed(0))["action"]
    assert out.shape == (1, 8, 7) and torch.isfinite(out).all()
