"""Scripted experts in robosuite: short episodes that check the expert actually manipulates the object."""
import numpy as np
import pytest


@pytest.fixture(scope="module")
def square_env():
    pytest.importorskip("robosuite")
    from robot_suite.tasks import make_env

    env = make_env("square")
    yield env
    env.close()


def test_square_expert_lifts_and_places_nut(square_env, one_thread):
    from robot_suite.experts import EXPERTS
    from robot_suite.tasks import reset_env

    env = square_env
    raw = reset_env(env, 0)
    expert = EXPERTS["square"](env)
    start_z = None
    lifted = success = False
    for t in range(200):
        raw, _, _, _ = env.step(expert.act(raw))
        if t == 10:
            start_z = raw["SquareNut_pos"][2]  # resting on the table
        if start_z is not None and raw["SquareNut_pos"][2] > start_z + 0.1:
            lifted = True
            handle = env.sim.data.site_xpos[env.object_site_ids[env.nut_id]]
            assert np.linalg.norm(raw["robot0_eef_pos"] - handle) < 0.03  # carried by the handle
            assert raw["robot0_gripper_qpos"][0] - raw["robot0_gripper_qpos"][1] < 0.035  # fingers closed on it
        if env._check_success():
            success = True
            break
    assert lifted, "the nut never rose 10 cm above the table"
    assert success and t < 150, f"nut not on the peg after {t + 1} steps (phase {expert.phase})"
    peg = env.sim.data.body_xpos[env.peg1_body_id]
    assert np.abs(raw["SquareNut_pos"][:2] - peg[:2]).max() < 0.03
