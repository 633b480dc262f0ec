"""Camera frames for recorded demonstrations (eval/render_demos.py): restored states render the
recorded scene, frames land in robomimic's image layout, and an interrupted run resumes."""
import json

import numpy as np
import pytest
import torch

import tts


@pytest.fixture(scope="module")
def lift_demos(tmp_path_factory):
    """Two short Lift demos (the expert's first 5 steps of seeds 0 and 1) in a low-dim hdf5 with a
    filter key; skipped where robosuite or offscreen rendering (EGL) is missing."""
    pytest.importorskip("robosuite")
    import collect_demos
    from robot_suite.robomimic import Demo, write_demos
    from robot_suite.tasks import env_args, make_env

    try:
        make_env("lift", cameras=("agentview",), image_size=16).close()
    except Exception as e:  # no EGL / GPU-less GL: nothing to render with
        pytest.skip(f"offscreen rendering unavailable: {e}")
    env = make_env("lift")
    demos = []
    for seed in (0, 1):
        _, d = collect_demos.run_expert(env, "lift", seed)
        demos.append(Demo(obs={k: v[:5] for k, v in d.obs.items()}, actions=d.actions[:5], rewards=d.rewards[:5],
                          dones=d.dones[:5], states=d.states[:5], attrs=d.attrs))
    env.close()
    path = tmp_path_factory.mktemp("demos") / "lift.hdf5"
    write_demos(path, demos, env_args("lift"), masks={"train": ["demo_1"]})
    return path


def test_rendered_demos_keep_everything_and_match_the_recorded_scene(lift_demos, tmp_path, one_thread):
    import render_demos
    from robot_suite.robomimic import read_demos, read_env_args, read_masks

    out = tmp_path / "lift_image.hdf5"
    report = render_demos.main(["--data", str(lift_demos), "--out", str(out), "--size", "24", "--chunk", "1"])
    src, dst = read_demos(lift_demos), read_demos(out)
    assert len(dst) == 2 and read_masks(out) == {"train": ["demo_1"]}
    for a, b in zip(src, dst):
        for cam in ("agentview_image", "robot0_eye_in_hand_image"):
            frames = b.obs[cam]
            assert frames.shape == (5, 24, 24, 3) and frames.dtype == np.uint8 and frames.std() > 5
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.obs["object"], b.obs["object"])
        assert b.attrs["seed"] == a.attrs["seed"]
    assert not np.array_equal(dst[0].obs["agentview_image"][0], dst[1].obs["agentview_image"][0])  # other scene
    # MuJoCo's step leaves positions one physics substep behind the integrated state: under a millimetre
    assert report["max_low_dim_difference"] < 2e-3 and report["frames"] == 10
    by_key = report["low_dim_difference_by_key"]
    assert {"object", "robot0_eef_pos", "robot0_gripper_qpos"} <= set(by_key)
    assert max(by_key.values()) == report["max_low_dim_difference"]
    args = read_env_args(out)["env_kwargs"]
    assert args["use_camera_obs"] and args["camera_names"] == ["agentview", "robot0_eye_in_hand"]
    assert args["camera_heights"] == 24 and json.loads(out.with_suffix(".json").read_text())["demos"] == 2
    assert not (tmp_path / "lift_image.hdf5.parts").exists()


def test_an_interrupted_render_resumes_from_its_finished_chunks(lift_demos, tmp_path, monkeypatch, one_thread):
    import render_demos

    calls = []
    real = render_demos.render_demo

    def failing(env, demo, cameras):
        if calls:
            raise KeyboardInterrupt
        calls.append(demo.attrs["seed"])
        return real(env, demo, cameras)

    out = tmp_path / "image.hdf5"
    args = ["--data", str(lift_demos), "--out", str(out), "--size", "16", "--chunk", "1", "--cameras", "agentview"]
    monkeypatch.setattr(render_demos, "render_demo", failing)
    with pytest.raises(KeyboardInterrupt):
        render_demos.main(args)
    assert not out.exists() and calls == [0]
    calls.clear()
    monkeypatch.setattr(render_demos, "render_demo", lambda env, demo, cams: (calls.append(demo.attrs["seed"]),
                                                                              real(env, demo, cams))[1])
    render_demos.main(args)
    assert calls == [1]  # demo 0's chunk was kept


def test_camera_frames_are_flipped_upright_and_missing_cameras_are_named():
    from robot_suite.tasks import camera_obs

    frame = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    out = camera_obs({"agentview_image": frame}, ["agentview"])
    np.testing.assert_array_equal(out["agentview_image"], frame[::-1])
    with pytest.raises(KeyError, match="robot0_eye_in_hand"):
        camera_obs({"agentview_image": frame}, ["agentview", "robot0_eye_in_hand"])


def test_a_camera_env_reset_collects_the_render_context_it_dropped(monkeypatch):
    from robot_suite import tasks

    collected = []
    monkeypatch.setattr(tasks.gc, "collect", lambda: collected.append(1) or 0)

    class Env:
        def __init__(self, cameras: bool):
            self.use_camera_obs = cameras

        def reset(self):
            return {"seed": int(self.rng.integers(1 << 30))}

    assert tasks.reset_env(Env(False), 3) == tasks.reset_env(Env(True), 3)  # same episode either way
    assert collected == [1]  # only the camera env's reset collects


def test_camera_envs_in_one_process_render_their_own_scene_across_hard_resets(lift_demos):
    """Two camera envs stepped in turn, each hard reset (which drops and frees a render context),
    render what a lone env renders: each binds its own GL context, and freeing a dropped context
    leaves the live one's buffers intact (freeing them gave wrong frames)."""
    from robot_suite.tasks import camera_obs, make_env, reset_env

    cams = ("agentview", "robot0_eye_in_hand")
    a, b = (make_env("lift", cameras=cams, image_size=32) for _ in range(2))
    for seed in (0, 1):
        frames = []
        for env in (a, b):
            reset_env(env, seed)
        for env in (a, b):
            frames.append(camera_obs(env.step(np.zeros(7))[0], cams))
        for k in frames[0]:
            assert frames[0][k].std() > 5  # a scene, not a blank buffer
            np.testing.assert_array_equal(frames[0][k], frames[1][k])
    a.close()
    b.close()


def test_robot_eval_renders_the_cameras_an_image_policy_reads(lift_demos, tmp_path, one_thread):
    """eval/robot.py on an image checkpoint: envs render its cameras at its image size, the frames
    reach the encoder once per call, and asking for low-dim observations is an error."""
    import robot
    from test_image_policy import image_policy
    from tts.adapters.dp_policy import save_policy

    save_policy(image_policy(steps=4), tmp_path / "img_policy", dtype=torch.float32,
                metadata={"note": "trained on demonstrations from a single scripted expert"})
    out = tmp_path / "run.json"
    args = ["--task", "lift", "--checkpoint", str(tmp_path / "img_policy"), "--episodes", "2", "--n-envs", "2",
            "--horizon", "3", "--out", str(out)]
    res = robot.main(args)
    assert res["obs_type"] == "image" and res["episodes_done"] == 2 and res["batch"] == 2
    assert res["policy_training_note"] == "trained on demonstrations from a single scripted expert"  # the checkpoint's own
    with pytest.raises(SystemExit):  # argparse's error: "... is an image policy"
        robot.main(args + ["--obs-type", "low_dim"])


def test_trajectories_of_an_image_policy_carry_its_camera_windows_and_replay(lift_demos, tmp_path, one_thread):
    """eval/collect_trajectories.py records an image policy's camera windows next to its low-dim
    window; a replay, the timing tools and the schedule search feed them back; low-dim-only data is a
    clear error."""
    import collect_trajectories
    from common.policy_timing import batch_frames
    from robot_suite.replay import replay
    from test_image_policy import image_policy
    from tts.adapters.dp_policy import load_policy, save_policy
    from tts.trajectories import load_trajectories, obs_dict

    save_policy(image_policy(steps=4), tmp_path / "img_policy", dtype=torch.float32)
    out = tmp_path / "traj.pt"
    collect_trajectories.main(["--task", "lift", "--checkpoint", str(tmp_path / "img_policy"), "--episodes", "2",
                               "--n-envs", "2", "--horizon", "10", "--out", str(out), "--full-horizon"])
    episodes, _ = load_trajectories(out, successful_only=False)
    ep = episodes[0]
    assert ep["agentview_image"].shape == (len(ep["obs"]), 2, 32, 32, 3) and ep["agentview_image"].dtype == np.uint8
    policy = load_policy(tmp_path / "img_policy")
    calls = []
    replay(policy, episodes, lambda frame, _: calls.append(frame.index))
    assert calls == list(range(len(ep["obs"])))
    frames = batch_frames(policy, episodes, 1)
    assert frames[0]["robot0_eye_in_hand_image"].shape == (2, 2, 32, 32, 3)
    import search_static  # the schedule search picks calls out of order, frames included

    sched = search_static.main(["--checkpoint", str(tmp_path / "img_policy"), "--trajectories",
                                str(out), "--sparsity", "0.5", "--objective", "output", "--calls", "3", "--batch", "3",
                                "--sweeps", "1", "--all-episodes", "--out", str(tmp_path / "steps.json")])
    assert len(json.loads((tmp_path / "steps.json").read_text())["compute_steps"]) == 2 and 0.5 in sched
    with pytest.raises(KeyError, match="no 'agentview_image' frames"):
        obs_dict(policy, torch.as_tensor(ep["obs"][:1]))
    import train_pruner  # a pruner trains on the recorded camera windows and then serves the image policy
    from test_image_policy import image_obs
    from tts.pruner import load_pruner

    train_pruner.main(["--trajectories", str(out), "--checkpoint", str(tmp_path / "img_policy"), "--out",
                       str(tmp_path / "pruner"), "--sparsity", "0.5", "--epochs", "1", "--batch", "1", "--n-train", "1",
                       "--n-val", "1", "--hidden", "16", "--all-episodes", "--run-dir", str(tmp_path / "run")])
    pr = load_pruner(tmp_path / "pruner")
    assert pr.metadata["n_train_episodes"] == 1 and len(pr.metadata["history"]) == 1
    encoded = []
    policy.obs_encoder.register_forward_hook(lambda m, a, o: encoded.append(a[0]["agentview_image"].shape[0]))
    seen = []  # what the pruner reads: the condition memory built from the one encoding of the call
    pr.register_forward_pre_hook(lambda m, a: seen.append(a[0].shape))
    with tts.accelerate(policy, pruner=pr) as acc:
        for c in range(3):
            policy.predict_action(image_obs(2, c), generator=torch.Generator().manual_seed(c))
        calls = acc.summary().calls
    assert encoded == [2 * 2] * 3  # once per call (2 samples x 2 frames), never inside the loop or for the pruner
    # calls 1 and 2 (call 0 is dense) on memory [B, K, Tc, D]; the batch-1 one is the MAC count's probe
    assert [tuple(s[:2]) for s in seen if s[0] == 2] == [(2, 4)] * 2
    assert calls[-1].timing["pruner"] > 0 and "wait" in calls[-1].timing


def test_a_camera_rollout_renders_only_the_frames_the_next_call_reads(lift_demos, monkeypatch, one_thread):
    """run_wave skips the camera renders of the steps whose frames no call reads (all but the last
    n_obs_steps of each action chunk): counted, and the windows every call reads are the frames of
    the same episode rendered at every step."""
    import robosuite.utils.binding_utils as binding
    from robot_suite.rollout import make_policy_envs, policy_cameras, run_wave
    from robot_suite.tasks import camera_obs, reset_env
    from test_image_policy import image_policy

    renders = []
    real_render = binding.MjSim.render
    monkeypatch.setattr(binding.MjSim, "render", lambda self, *a, **k: renders.append(1) or real_render(self, *a, **k))
    policy = image_policy(steps=2)
    chunk, window = policy.cfg.n_action_steps, policy.cfg.n_obs_steps
    cams = policy_cameras(policy)
    env = make_policy_envs(policy, "lift", 1)[0]
    renders.clear()
    (out,), _ = run_wave(policy, [env], [7], "lift", None, record=True, horizon=2 * chunk)
    skipping = len(renders)
    traj = out["trajectory"]
    assert len(traj["action"]) == 2 and not out["success"]

    renders.clear()  # the reference: the same episode, every step rendered and observed
    frames = [camera_obs(reset_env(env, 7), cams)]
    for call in range(2):
        for k in (f"{c}_image" for c in cams):
            expected = np.stack([f[k] for f in ([frames[0]] * window + frames)[-window:]])
            np.testing.assert_array_equal(traj[k][call], expected)
        for a in traj["action"][call]:
            frames.append(camera_obs(env.step(a)[0], cams))
    every_step = len(renders)
    env.close()
    assert len(cams) == 2 and every_step - skipping == len(cams) * 2 * (chunk - window)  # x 2 chunks x unread steps
