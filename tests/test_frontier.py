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


def test_call_latency_rows_and_the_device_it_ran_on(tmp_path):
    import latency
    import torch

    _toy_policy_and_trajectories(tmp_path, [3, 3])
    out = tmp_path / "l.json"
    base = ["--task", "toy", "--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
            "--first-episode", "0", "--trials", "2", "--frames", "2", "--out", str(out), "--batch", "2"]
    res = latency.main(base + ["--method", "uniform:0.5:timestep"])
    (r,) = res["rows"]
    assert r["speedup"] == pytest.approx(r["dense_ms"]["median"] / r["accelerated_ms"]["median"])
    assert r["dense_ms"]["calls"] == r["accelerated_ms"]["calls"] == 2 * 2 and r["sparsity"] == pytest.approx(0.5)
    assert r["actions_per_s_per_env"]["dense"] == pytest.approx(r["calls_per_s"]["dense"] * 8)
    assert res["device"] == "cpu" and json.loads(out.read_text()) == res
    if not torch.cuda.is_available():  # a GPU that is not there is an error, not a silent CPU run
        with pytest.raises(SystemExit, match="no such CUDA device"):
            latency.main(base + ["--method", "ddim:2", "--device", "cuda"])


def test_frontier_latency_rejects_a_method_listed_twice(tmp_path):
    import frontier_latency

    with pytest.raises(SystemExit):
        frontier_latency.main(["--task", "toy", "--checkpoint", "x", "--trajectories", "y", "--methods", "ddim:2",
                               "ddim:2"])


def test_results_record_the_sent_commit_where_a_copied_checkout_says_otherwise(monkeypatch):
    """A checkout copied to a GPU machine may carry a stale .git; the sender's TTS_GIT_SHA wins."""
    from common import git_sha

    monkeypatch.delenv("TTS_GIT_SHA", raising=False)
    here = git_sha()
    monkeypatch.setenv("TTS_GIT_SHA", "0123abc")
    assert git_sha() == "0123abc" != here


def test_results_record_the_commit_a_run_started_from_not_a_later_one(monkeypatch):
    """A long evaluation writes its rows while new commits land; the SHA it records is the code it
    runs, read when it started."""
    import subprocess

    from common import git_sha

    monkeypatch.delenv("TTS_GIT_SHA", raising=False)
    started = git_sha()
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0, "f" * 40 + "\n", ""))
    assert git_sha() == started and not started.startswith("f" * 40)


def _run(folder, method, successes, seed=100000, task="lift"):
    eps = [{"seed": seed + i, "success": bool(s)} for i, s in enumerate(successes)]
    doc = {"task": task, "checkpoint": f"checkpoints/{task}_dpt", "method": method, "episodes_requested": len(eps),
           "episodes_done": len(eps), "success_rate": sum(successes) / len(eps),
           "provenance": {"seeds": [e["seed"] for e in eps]}, "episodes": eps}
    (folder / f"{task}_{method.replace(':', '-')}_{seed}.json").write_text(json.dumps(doc))


def test_frontier_join_dominance_and_the_fewer_steps_verdict(tmp_path):
    from common import frontier

    n = 60
    _run(tmp_path, "dense", [1] * n)
    _run(tmp_path, "ddim:2", [1] * 30 + [0] * 30)  # fastest, poor
    _run(tmp_path, "ddim:5", [1] * 45 + [0] * 15)
    _run(tmp_path, "uniform:0.9:timestep", [1] * 58 + [0] * 2)  # as fast as ddim:5, much better
    _run(tmp_path, "uniform:0.8:timestep", [1] * 40 + [0] * 20)  # slower than ddim:5 and worse: dominated
    _run(tmp_path, "ddim:5", [1] * 10, seed=400000)  # a validation run never pools with the test runs
    rows = [{"method": m, "batch": 1, "latency_ms": 1000 / s, "speedup": s, "dense_ms": 1000.0, "computed_steps": c}
            for m, s, c in (("ddim:2", 40.0, 2), ("ddim:5", 18.0, 5), ("uniform:0.9:timestep", 18.0, 10),
                            ("uniform:0.8:timestep", 9.0, 20))]
    (tmp_path / "frontier_latency_lift.json").write_text(json.dumps({"rows": rows}))
    pts = {p.method: p for p in frontier.frontier_points(tmp_path, "lift", 1)}
    assert set(pts) == {"dense", "ddim:2", "ddim:5", "uniform:0.9:timestep", "uniform:0.8:timestep"}
    assert pts["ddim:5"].episodes == n and pts["dense"].speedup == 1.0
    on = {m for m, p in pts.items() if frontier.on_frontier(p, list(pts.values()))}
    assert on == {"dense", "ddim:2", "uniform:0.9:timestep"}
    best, diff, lo, hi = frontier.beats_fewer_steps(pts["uniform:0.9:timestep"], list(pts.values()))
    assert best.method == "ddim:5" and diff == pytest.approx(13 / 60) and lo > 0
    best, diff, lo, _ = frontier.beats_fewer_steps(pts["uniform:0.8:timestep"], list(pts.values()))
    assert best.method == "ddim:5" and diff < 0 and lo < 0
    assert frontier.frontier_points(tmp_path, "lift", 28) == []
    # a sampler 3% slower than a sparse method is within the timing noise: it is its rival
    slower = frontier.Point("ddim:6", 0.99, n, (0.9, 1.0), 9.0 * 0.97, 1.0, 6, pts["ddim:5"].runs)
    assert frontier.beats_fewer_steps(pts["uniform:0.8:timestep"], [*pts.values(), slower])[0] is slower
    specs = ("dense", "ddim:3", "ddim:3:leading", "ddim:3:trailing", "dpm:2", "ddpm:7", "file:x+ddim:20")
    assert [frontier.family(m) for m in specs] == ["dense", "ddim", "ddim", "ddim-trailing", "dpm", "ddpm", "sparse"]
    # every sampler of the method vocabulary is a fewer-step family (an explicit default spacing is the plain one)
    assert set(frontier.SAMPLER_FAMILIES) >= {"ddim", "ddim-trailing", "dpm", "ddpm"}
    # the stochastic fewer-step DDPM is a rival like the others
    ddpm = frontier.Point("ddpm:6", 1.0, n, (0.95, 1.0), 9.5, 1.0, 6, pts["ddim:5"].runs)
    assert frontier.beats_fewer_steps(pts["uniform:0.8:timestep"], [*pts.values(), ddpm])[0] is ddpm


def test_a_win_is_no_verdict_while_a_sampler_with_runs_and_no_more_steps_is_untimed(tmp_path):
    """Latencies timed elsewhere (a GPU's folder) join the same success runs; a sparse point that beats
    the timed samplers is not called a win while a sampler with test runs and at most as many steps
    was not timed there."""
    import tables
    from common import frontier

    n = 60
    _run(tmp_path, "dense", [1] * n)
    _run(tmp_path, "ddim:5", [1] * 45 + [0] * 15)
    _run(tmp_path, "uniform:0.9:timestep", [1] * 58 + [0] * 2)
    _run(tmp_path, "dpm:8", [1] * 59 + [0])  # run on the test seeds, not timed on the GPU
    _run(tmp_path, "dpm:20", [1] * n)  # more steps than the sparse point computes: not its rival
    gpu = tmp_path / "gpu"
    gpu.mkdir()
    rows = [{"method": m, "batch": 1, "latency_ms": 1000 / s, "speedup": s, "dense_ms": 1000.0, "computed_steps": c}
            for m, s, c in (("ddim:5", 18.0, 5), ("uniform:0.9:timestep", 18.0, 10))]
    (gpu / "frontier_latency_lift.json").write_text(json.dumps({"task": "lift", "policy": "lift",
                                                                "checkpoint": "checkpoints/lift_dpt", "rows": rows}))
    assert frontier.frontier_points(tmp_path, "lift", 1) == []  # no CPU latency file
    pts = frontier.frontier_points(tmp_path, "lift", 1, gpu)
    assert list(frontier.untimed_samplers(tmp_path, "lift", pts).items()) == [("dpm:8", 8), ("dpm:20", 20)]
    row = next(r for r in tables.frontier_table(tmp_path, gpu).splitlines() if "uniform:0.9" in r)
    assert "no verdict: `dpm:8` not timed here" in row and "beats it" not in row
    (gpu / "frontier_latency_lift.json").write_text(json.dumps({"task": "lift", "policy": "lift",
                                                                "checkpoint": "checkpoints/lift_dpt", "rows": rows + [
        {"method": "dpm:8", "batch": 1, "latency_ms": 100.0, "speedup": 10.0, "dense_ms": 1000.0, "computed_steps": 8}]}))
    row = next(r for r in tables.frontier_table(tmp_path, gpu).splitlines() if "uniform:0.9" in r)
    assert "beats it" in row and "no verdict" not in row  # dpm:8 timed, and slower: ddim:5 is the rival


def test_frontier_of_a_coverage_policy_scores_mean_coverage_with_paired_differences(tmp_path):
    """Push-T runs record goal coverage: the frontier scores the mean best coverage per episode, and
    the verdict against fewer steps is the paired coverage difference on the same episodes."""
    from common import frontier
    from helpers import write_coverage_run

    write_coverage_run(tmp_path, "dense", [0.6, 0.7, 0.8, 0.5])
    write_coverage_run(tmp_path, "dpm:7", [0.4, 0.5, 0.6, 0.5])
    write_coverage_run(tmp_path, "uniform:0.93:timestep", [0.5, 0.6, 0.7, 0.6])  # +0.1 on every episode, as fast
    rows = [{"method": m, "batch": 1, "latency_ms": 10.0, "speedup": 14.0, "dense_ms": 140.0, "computed_steps": 7}
            for m in ("dpm:7", "uniform:0.93:timestep")]
    (tmp_path / "frontier_latency_pusht-pusht_mh_dpt_17k.json").write_text(json.dumps({"rows": rows}))
    pts = {p.method: p for p in frontier.frontier_points(tmp_path, "pusht (pusht_mh_dpt_17k)", 1)}
    assert {p.metric for p in pts.values()} == {"coverage"}
    assert pts["dense"].score == pytest.approx(0.65) and pts["dpm:7"].score == pytest.approx(0.5)
    lo, hi = pts["dense"].interval
    assert 0 <= lo < 0.65 < hi <= 1
    best, diff, lo, hi = frontier.beats_fewer_steps(pts["uniform:0.93:timestep"], list(pts.values()))
    assert best.method == "dpm:7" and diff == pytest.approx(0.1) and lo == pytest.approx(0.1) == hi
    assert not frontier.on_frontier(pts["dpm:7"], list(pts.values()))


def test_searched_steps_on_a_shorter_base_sampler(tmp_path):
    """eval/search_static.py --sampler ddim:4: the schedule has the base's 4 steps, and it runs as
    file:SCHEDULE+ddim:4 (a file made for the policy's own 6 steps says it does not fit)."""
    import search_static
    import torch

    from common.methods import ROBOT_KINDS, install_policy, parse_method
    from test_robot_pipeline import obs_batch
    from tts.adapters.dp_policy import load_policy

    _toy_policy_and_trajectories(tmp_path, [3, 4])
    out = tmp_path / "steps.json"
    search_static.main(["--checkpoint", str(tmp_path / "policy"), "--trajectories", str(tmp_path / "traj.pt"),
                        "--sampler", "ddim:4", "--sparsity", "0.5", "--objective", "output", "--calls", "4",
                        "--shifts", "1", "--sweeps", "1", "--out", str(out)])
    doc = json.loads(out.read_text())
    assert len(doc["grid"]) == 4 and doc["sampler"] == "ddim:4"
    assert sum(set(row) == {"C"} for row in doc["grid"]) == 2
    pol = load_policy(tmp_path / "policy")
    with install_policy(pol, parse_method(f"file:{out}+ddim:4", kinds=ROBOT_KINDS)) as acc:
        pol.predict_action(obs_batch(2), torch.Generator().manual_seed(0))
        assert len(acc.summary().calls[-1].steps) == 4
    pol.set_sampler("ddpm", 6)
    with install_policy(pol, parse_method(f"file:{out}", kinds=ROBOT_KINDS)):
        with pytest.raises(IndexError, match="only has 4 steps"):
            pol.predict_action(obs_batch(2))
    pol.set_sampler("ddim", 3)  # a loop shorter than the schedule: not silent either
    with install_policy(pol, parse_method(f"file:{out}", kinds=ROBOT_KINDS)) as acc:
        pol.predict_action(obs_batch(2))
        with pytest.warns(UserWarning, match="made for 4 denoising steps but a sampling call ran 3"):
            acc.summary()


def test_image_frontier_lower_fid_is_better_and_the_verdict_is_conservative(tmp_path):
    """Image points: FID runs joined with one latency file; lower FID dominates; a sparse method beats
    the best fewer-step sampler as fast only when the combined interval lies below zero."""
    import tables
    from common import frontier

    def run(method, fid, lo, hi, steps=50):
        (tmp_path / f"digits_{method.replace(':', '-')}.json").write_text(json.dumps(
            {"method": method, "fid": fid, "fid_interval": [lo, hi], "sfid": fid + 1, "num_samples": 2000,
             "steps": steps}))

    run("dense", 40.0, 38.0, 42.0)
    run("ddim:5", 90.0, 85.0, 95.0, steps=5)
    run("ddim:10", 60.0, 57.0, 63.0, steps=10)
    run("every_n:2:timestep", 45.0, 43.0, 47.0)  # as fast as ddim:10, clearly better
    run("every_n:3:timestep", 61.0, 58.0, 64.0)  # as fast as ddim:10, no better: dominated
    run("toca:6@0.8", 59.0, 56.0, 62.0)  # not in the latency file: no point
    methods = {"ddim:5": 10.0, "ddim:10": 5.0, "every_n:2:timestep": 5.0, "every_n:3:timestep": 5.0}
    latency = tmp_path / "frontier_latency.json"
    latency.write_text(json.dumps({"rows": [{"batch": 16, "dense_ms": 100.0, "methods": {
        m: {"ms": 100.0 / s, "speedup": s, "sampler": "ddim:50"} for m, s in methods.items()}}]}))
    pts = {p.method: p for p in frontier.image_frontier_points(tmp_path, latency, 16)}
    assert set(pts) == {"dense", *methods} and pts["dense"].speedup == 1.0 and pts["ddim:5"].interval == (85.0, 95.0)
    on = {m for m, p in pts.items() if frontier.on_frontier(p, list(pts.values()))}
    assert on == {"dense", "ddim:5", "every_n:2:timestep"}
    best, diff, lo, hi = frontier.beats_fewer_steps(pts["every_n:2:timestep"], list(pts.values()))
    assert best.method == "ddim:10" and (diff, lo, hi) == (-15.0, -20.0, -10.0)
    assert frontier.beats_fewer_steps(pts["every_n:3:timestep"], list(pts.values()))[3] > 0
    table = tables.image_frontier_table(tmp_path)
    assert "`every_n:2:timestep` | 50 | 45.00 [43.00, 47.00]" in table and table.count("**beats it**") == 1
    assert frontier.image_frontier_points(tmp_path, latency, 1) == []


def test_image_headline_holds_each_sparse_row_against_the_best_sampler_as_fast(tmp_path):
    """README image table: speed-ups from the frontier's latencies (they replace latency.json's), the
    sampler a headline sparse row is held against shown as a row of its own, and the verdict column."""
    import tables

    def run(method, fid, lo, hi, steps=50):
        (tmp_path / f"digits_{method.replace(':', '-')}.json").write_text(json.dumps(
            {"method": method, "fid": fid, "fid_interval": [lo, hi], "num_samples": 2000, "steps": steps,
             "macs_dense_per_image": 100.0 * steps, "macs_realised_per_image": 100.0 * steps / 5,
             "macs_pruner_per_image": 0.0}))

    run("dense", 40.0, 38.0, 42.0)
    run("ddim:10", 60.0, 57.0, 63.0, steps=10)
    run("ddim:8", 65.0, 62.0, 68.0, steps=8)
    run("every_n:5:timestep", 90.0, 87.0, 93.0)  # as fast as ddim:8 only: held against it, and loses
    run("file:digits_steps_0.8+taylor2", 43.0, 41.0, 45.0)  # as fast as ddim:10, and beats it
    (tmp_path / "latency.json").write_text(json.dumps({"rows": [
        {"batch": 1, "dense_ms": 100.0, "methods": {"every_n:5:timestep": {"speedup": 9.9}}}]}))
    speed = {"ddim:10": 5.0, "ddim:8": 6.0, "every_n:5:timestep": 6.0, "file:digits_steps_0.8+taylor2": 4.9}
    (tmp_path / "frontier_latency.json").write_text(json.dumps({"rows": [{"batch": b, "dense_ms": 100.0, "methods": {
        m: {"ms": 100.0 / s, "speedup": s * b} for m, s in speed.items()}} for b in (1, 16)]}))
    lines = tables.headline_image(tmp_path).strip().splitlines()
    assert lines[0].endswith("| wall-clock speed-up, batch 1 | wall-clock speed-up, batch 16 "
                             "| minus the best fewer-step sampler as fast, batch 1 (95% CI) |")
    names = [line.split("`")[1] for line in lines[2:]]
    assert names == ["dense", "ddim:10", "ddim:8", "every_n:5:timestep", "file:digits_steps_0.8+taylor2"]
    assert "| `every_n:5:timestep` | 90.00 | 5.00x | 6.00x | 96.00x | `ddim:8`: +25.00 (+19.00, +31.00) |" in lines
    assert lines[-1].endswith("| 4.90x | 78.40x | `ddim:10`: -17.00 (-22.00, -12.00) **beats it** |")


def test_image_frontier_figure_draws_intervals_that_lie_below_the_fid(tmp_path, monkeypatch):
    """The FID's basic-bootstrap interval can lie wholly below the 2000-sample FID (the estimate's upward
    bias): the figure must still draw it (matplotlib's error bars refuse negative lengths)."""
    import figures

    folder = tmp_path / "results" / "image"
    folder.mkdir(parents=True)
    for method, fid, steps in (("dense", 42.5, 50), ("ddim:10", 51.6, 10), ("dpm:10", 47.0, 10),
                               ("every_n:2:timestep", 45.2, 50)):
        (folder / f"digits_{method.replace(':', '-')}.json").write_text(json.dumps(
            {"method": method, "fid": fid, "fid_interval": [fid - 3.4, fid - 1.1], "num_samples": 2000, "steps": steps}))
    (folder / "frontier_latency.json").write_text(json.dumps({"rows": [{"batch": 1, "dense_ms": 100.0, "methods": {
        "ddim:10": {"ms": 20.0, "speedup": 5.0}, "dpm:10": {"ms": 21.0, "speedup": 4.8},
        "every_n:2:timestep": {"ms": 50.0, "speedup": 2.0}}}]}))
    monkeypatch.setattr(figures, "REPO", tmp_path)
    monkeypatch.setattr(figures, "DOCS", tmp_path)
    out = figures.image_frontier(None)
    assert out == tmp_path / "frontier_digits.png" and out.stat().st_size > 10_000
