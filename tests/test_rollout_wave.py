"""eval/robot_suite/rollout.run_wave on a fake env: stop at success, or run to the horizon."""
import numpy as np

from test_robot_pipeline import OBS_DIMS, small_policy


class FakeEnv:
    """Succeeds once it has taken ``solve_at`` steps; observations are the step count."""

    def __init__(self, solve_at: int):
        self.solve_at, self.t = solve_at, 0

    def obs(self):
        return {k: np.full(d, float(self.t), dtype=np.float32) for k, d in OBS_DIMS.items()}

    def step(self, action):
        self.t += 1
        return self.obs(), 0.0, False, {}

    def _check_success(self):
        return self.t >= self.solve_at


def test_full_horizon_keeps_recording_after_success(monkeypatch, one_thread):
    from robot_suite import rollout

    monkeypatch.setattr(rollout, "reset_env", lambda env, seed: (setattr(env, "t", 0), env.obs())[1])
    monkeypatch.setattr(rollout, "low_dim_obs", lambda raw: raw)
    policy = small_policy(num_steps=4)
    ta = policy.cfg.n_action_steps
    envs = [FakeEnv(solve_at=ta + 2), FakeEnv(solve_at=10 ** 6)]
    short, _ = rollout.run_wave(policy, envs, [0, 1], "lift", None, record=True, horizon=4 * ta)
    full, _ = rollout.run_wave(policy, envs, [0, 1], "lift", None, record=True, horizon=4 * ta, full_horizon=True)
    assert [o["success"] for o in short] == [True, False] == [o["success"] for o in full]
    # stopping at success: env 0 recorded 2 calls and stopped stepping; to the horizon: all 4 calls
    assert len(short[0]["trajectory"]["obs"]) == 2 and short[0]["env_steps"] == ta + 2
    assert len(full[0]["trajectory"]["obs"]) == 4 and full[0]["env_steps"] == 4 * ta
    assert len(short[1]["trajectory"]["obs"]) == len(full[1]["trajectory"]["obs"]) == 4
