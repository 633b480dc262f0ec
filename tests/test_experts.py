"""Scripted experts in robosuite: short episodes that check the expert actually manipulates the object."""
import numpy as np
import pytest


def _env(task: str):
    """One robosuite env of ``task`` for a test module (skipped without robosuite)."""
    pytest.importorskip("robosuite")
    from robot_suite.tasks import make_env

    env = make_env(task)
    yield env
    env.close()


@pytest.fixture(scope="module")
def square_env():
    yield from _env("square")


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


@pytest.fixture(scope="module")
def lift_env():
    yield from _env("lift")


def _episode(env, expert, seed, steps):
    from robot_suite.tasks import reset_env

    raw = reset_env(env, seed)
    first_yaw, actions = None, []
    for _ in range(steps):
        a = expert.act(raw)
        actions.append(a)
        if first_yaw is None:
            from robot_suite.experts import _yaw

            first_yaw = _yaw(raw["robot0_eef_quat"])
        raw, _, _, _ = env.step(a)
    return raw, np.array(actions), first_yaw


def test_operator_styles_change_behaviour(lift_env, one_thread):
    """A counter-clockwise operator turns the hand up to 90 deg CCW before grasping and comes via its
    via point; a hesitant one records still steps; one that always misses gives up and never lifts."""
    from robot_suite.experts import Operator, _yaw, make_expert

    ccw = Operator("ccw", "better", yaw=np.pi / 4, approach=(0.0, 0.08))
    expert = make_expert("lift", lift_env, ccw, np.random.default_rng(0))
    raw, actions, yaw0 = _episode(lift_env, expert, 3, 90)
    turn = (_yaw(raw["robot0_eef_quat"]) - yaw0 + np.pi) % (2 * np.pi) - np.pi
    assert 0.3 < turn < np.pi / 2 + 0.1  # this cube's CCW face alignment is ~70 deg away
    assert abs(_yaw(raw["robot0_eef_quat"]) - expert.yaw) < 0.05
    assert expert._via_done and expert.phase == 3
    assert raw["cube_pos"][2] > 0.86  # lifted

    shaky = Operator("shaky", "worse", hesitate=0.2, pause=(3, 3))
    _, actions, _ = _episode(lift_env, make_expert("lift", lift_env, shaky, np.random.default_rng(0)), 3, 40)
    still = np.all(actions[:, :6] == 0, axis=1)
    assert 5 <= still.sum() < 40

    hopeless = Operator("hopeless", "worse", miss=1.0, max_grasps=1)
    expert = make_expert("lift", lift_env, hopeless, np.random.default_rng(0))
    raw, _, _ = _episode(lift_env, expert, 3, 150)
    assert expert.gave_up and expert.failed_grasps == 1
    assert raw["cube_pos"][2] < 0.84 and not lift_env._check_success()


def test_collect_mh_writes_masks_and_report(tmp_path, monkeypatch, one_thread):
    pytest.importorskip("robosuite")
    import collect_demos
    from robot_suite.experts import Operator
    from robot_suite.robomimic import read_demos

    ops = [Operator("better_operator_1", "better"), Operator("worse_operator_1", "worse", yaw=0.3, noise=0.1)]
    monkeypatch.setitem(collect_demos.OPERATORS, "lift", ops)
    out, report = tmp_path / "mh.hdf5", tmp_path / "mh.json"
    collect_demos.main(["--task", "lift", "--mix", "mh", "--episodes", "2", "--per-operator", "1",
                        "--out", str(out), "--report", str(report)])
    demos = read_demos(out)
    assert [d.attrs["operator"] for d in demos] == ["better_operator_1", "worse_operator_1"]
    assert [d.attrs["seed"] for d in demos] == [0, 2]  # operator k starts at seed + k * episodes
    assert [len(read_demos(out, filter_key=k)) for k in ("better", "okay", "worse", "worse_better")] == [1, 0, 1, 2]
    assert read_demos(out, filter_key="worse_operator_1")[0].attrs["quality"] == "worse"
    rows = __import__("json").loads(report.read_text())["operators"]
    assert [r["attempts"] for r in rows] == [2, 2] and rows[0]["success_rate"] == 1.0
    assert not (tmp_path / "mh.hdf5.parts").exists()
