"""Push-T: the scene wrapper, the scripted pusher and the data/training path for its keys."""
import numpy as np
import pytest

pytest.importorskip("gym_pusht")

from robot_suite import pusht  # noqa: E402
from robot_suite.tasks import TASKS, low_dim_obs, make_env, reset_env, sim_state, task_of_env  # noqa: E402


def test_reset_to_reproduces_a_state_exactly():
    """gym-pusht's own reset_to_state sets the angle after the position, which turns the block about
    its centre of mass and moves it; the scene's reset_to must not."""
    scene = pusht.PushTScene()
    obs = scene.reset_seed(3)
    for _ in range(5):
        obs = scene.step(obs["state"][:2] + 30.0)[0]
    copy = pusht.PushTScene().reset_to(obs["state"])
    np.testing.assert_allclose(copy["state"], obs["state"], atol=1e-9)
    raw = pusht.make_pusht()
    raw.reset(options={"reset_to_state": obs["state"]})
    assert np.abs(raw.get_obs()[2:4] - obs["state"][2:4]).max() > 1.0  # the library's own reset moves it


def test_the_recorded_state_of_a_push_t_step_restores_its_scene():
    """collect_demos records sim_state per step (the dataset's ``states``): for the task's own env,
    reset_to of that state gives back the same observation."""
    env = make_env("pusht")
    raw = reset_env(env, 11)
    for _ in range(3):
        raw = env.step(raw["state"][:2] + 20.0)[0]
    state = sim_state(env, raw)
    again = make_env("pusht").reset_to(state)
    for k in TASKS["pusht"].obs_keys:
        np.testing.assert_allclose(low_dim_obs(again)[k], low_dim_obs(raw)[k], atol=1e-5)


def test_keypoints_match_the_block_shapes_and_the_goal_scores_full_coverage():
    scene = pusht.PushTScene()
    scene.reset_seed(5)
    corners = np.array([scene.env.block.local_to_world(tuple(v)) for v in pusht.T_OUTLINE])
    np.testing.assert_allclose(corners, pusht.keypoints(scene.env.get_obs()[2:]), atol=1e-9)
    assert pusht.keypoint_error(pusht.GOAL) == 0.0
    scene.reset_to(np.concatenate([[50.0, 50.0], pusht.GOAL]))
    scene.step(np.array([50.0, 50.0]))
    assert scene._check_success() and scene.coverage > 0.99


def test_scripted_pusher_solves_an_episode_within_the_horizon(one_thread):
    env = make_env("pusht")
    raw = reset_env(env, 0)
    expert = pusht.PushTExpert(env)
    for t in range(TASKS["pusht"].horizon):
        raw = env.step(expert.act(raw))[0]
        if env._check_success():
            break
    assert env._check_success(), f"coverage {env.coverage:.2f} after {t + 1} steps"
    assert set(low_dim_obs(raw)) == set(TASKS["pusht"].obs_keys) and low_dim_obs(raw)["block_keypoints"].shape == (16,)


def test_route_preference_picks_the_side_around_the_block():
    """Both directions around the block reach the same point; the operator's preference picks one."""
    scene = pusht.PushTScene()
    scene.reset_to(np.array([256.0, 100.0, 256.0, 256.0, 0.0]))
    ends = {}
    for side in (+1, -1):
        ex = pusht.PushTExpert(scene, pusht.PushOperator(route=side, route_bias=1.0))
        ex._pose = np.array([256.0, 256.0, 0.0])
        path = ex._route(np.array([256.0, 150.0]), np.array([256.0, 420.0]), np.array([256.0, 300.0]), 110.0)
        ends[side] = np.mean([q[0] for q in path[:-1]])
    assert ends[+1] > 300 and ends[-1] < 212  # counter-clockwise passes right (+x), clockwise left


def test_datasets_name_their_task():
    assert task_of_env("PushT") == "pusht" and task_of_env("Lift") == "lift"
    with pytest.raises(ValueError, match="no task for env"):
        task_of_env("Transport")


def test_policy_rollout_on_push_t_reports_coverage(one_thread):
    import torch
    from robot_suite.rollout import run_wave
    from tts.adapters.dp_policy import DiffusionTransformerLowdimPolicy, PolicyConfig

    cfg = PolicyConfig(
        model=dict(input_dim=2, output_dim=2, horizon=10, n_obs_steps=2, cond_dim=18, n_layer=1, n_head=2, n_emb=16,
                   p_drop_emb=0.0, p_drop_attn=0.0, causal_attn=True, obs_as_cond=True),
        obs_keys=list(TASKS["pusht"].obs_keys), obs_dims=[2, 16], action_dim=2, num_inference_steps=2)
    policy = DiffusionTransformerLowdimPolicy(cfg)
    policy.obs_normalizer.fit(torch.rand(50, 18) * 512)
    policy.action_normalizer.fit(torch.rand(50, 2) * 512)
    envs = [make_env("pusht") for _ in range(2)]
    outcomes, latencies = run_wave(policy.eval(), envs, [7, 8], "pusht", torch.Generator().manual_seed(0), horizon=16)
    assert [o["env_steps"] for o in outcomes] == [16, 16] and len(latencies) == 2
    assert all(0.0 <= o["max_coverage"] <= 1.0 and not o["success"] for o in outcomes)
