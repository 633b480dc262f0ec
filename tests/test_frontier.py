"""The frontier's latency runner: many methods against one dense reference in one process."""
import json

import pytest

from test_pruner import _toy_policy_and_trajectories


def test_frontier_latency_rows_and_resume(tmp_path):
    import frontier_latency

    _toy_policy_and_trajectories(tmp_path, [3, 3])
    out = tmp_path / "f.json"
    base = ["--task", "toy", "--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
            "--first-episode", "0", "--trials", "2", "--frames", "2", "--out", str(out)]
    res = frontier_latency.main(base + ["--batch", "1", "2", "--methods", "ddim:2", "uniform:0.5:timestep+ddim:4"])
    rows = {(r["method"], r["batch"]): r for r in res["rows"]}
    assert set(rows) == {(m, b) for m in ("ddim:2", "uniform:0.5:timestep+ddim:4") for b in (1, 2)}
    assert rows[("ddim:2", 1)]["computed_steps"] == 2 and rows[("ddim:2", 1)]["sampler"] == "ddim-2"
    assert rows[("uniform:0.5:timestep+ddim:4", 2)]["computed_steps"] == 2
    r = rows[("ddim:2", 2)]
    assert r["speedup"] == pytest.approx(r["dense_ms"] / r["latency_ms"]) and r["calls"] == 2 * 2
    assert res["provenance"]["command"] and res["policy"] == "toy-policy"
    # --resume keeps finished rows and adds only the new method
    again = frontier_latency.main(base + ["--batch", "1", "--methods", "ddim:2", "dpm:2", "--resume"])
    rows2 = {(r["method"], r["batch"]): r for r in again["rows"]}
    assert rows2[("ddim:2", 1)] == rows[("ddim:2", 1)] and ("dpm:2", 1) in rows2
    assert json.loads(out.read_text()) == again


def test_frontier_latency_rejects_a_method_listed_twice(tmp_path):
    import frontier_latency

    with pytest.raises(SystemExit):
        frontier_latency.main(["--task", "toy", "--checkpoint", "x", "--trajectories", "y", "--methods", "ddim:2",
                               "ddim:2"])
