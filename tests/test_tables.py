"""eval/tables.py and eval/figures.py: the paired comparison with dense (Newcombe interval, sign test) and
the data-efficiency series."""
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

from common.stats import newcombe_paired, paired_success_difference, sign_test_p  # noqa: E402


def run(outcomes: dict[int, bool]) -> dict:
    return {"episodes": [{"seed": s, "success": ok} for s, ok in outcomes.items()]}


def test_paired_difference_counts_discordant_episodes_on_common_seeds_only():
    dense = [run({1: True, 2: True, 3: False, 4: True})]
    mine = [run({1: True, 2: False}), run({3: True, 4: False, 99: True})]  # seed 99: no dense episode
    text = paired_success_difference(mine, dense)
    assert text.startswith("-0.250 (") and text.endswith("on 4; 2 / 1, p = 1")
    lo, hi = (float(x) for x in text.split("(")[1].split(")")[0].split(", "))
    assert lo < -0.25 < hi


def test_identical_outcomes_give_a_symmetric_interval_that_narrows_with_episodes_and_no_overlap_is_reported():
    dense = [run({1: True, 2: False})]
    assert paired_success_difference([run({1: True, 2: False})], dense) == "+0.000 (-0.573, +0.573) on 2; 0 / 0, p = 1"
    # all 150 solved by both: not a zero-width interval (the normal approximation's), about +-0.025
    diff, lo, hi = newcombe_paired(150, 0, 0, 0)
    assert diff == 0 and lo == -hi and 0.02 < hi < 0.03
    assert paired_success_difference([run({5: True})], dense) == "no common episodes"
    with pytest.raises(KeyError):
        paired_success_difference([{"episodes": [{"seed": 1}]}], dense)


def test_newcombe_interval_moves_with_the_discordant_pairs_and_stays_in_range():
    # the Can TTS row: 262 both, 7 only TTS, 17 only dense, 14 neither
    diff, lo, hi = newcombe_paired(262, 7, 17, 14)
    assert abs(diff + 10 / 300) < 1e-12 and -0.07 < lo < diff < hi < 0
    _, lo2, hi2 = newcombe_paired(262, 9, 15, 14)  # fewer losses: the interval moves up and covers 0
    assert lo2 > lo and hi2 > 0
    assert newcombe_paired(0, 0, 150, 0)[:2] == (-1.0, -1.0)  # never solved vs always solved
    assert newcombe_paired(0, 150, 0, 0)[2] == 1.0


def test_sign_test_is_exact_two_sided_binomial():
    assert sign_test_p(0, 0) == 1.0 and sign_test_p(1, 0) == 1.0
    assert sign_test_p(5, 0) == sign_test_p(0, 5) == 2 / 32
    assert abs(sign_test_p(17, 7) - 0.0639) < 1e-4  # 2 * P(X <= 7), X ~ Bin(24, 1/2)


def test_data_efficiency_pipeline_is_told_apart_by_the_priors_calibration_trajectories():
    from figures import _prior_calibration
    assert _prior_calibration("results/schedules/lift_steps_0.93_4traj.json") == 4
    assert _prior_calibration("results/schedules/lift_steps_0.93.json") == 32  # the table's schedule
    assert _prior_calibration(None) is None
    assert _prior_calibration("results/schedules/missing.json") is None


def test_data_efficiency_keeps_schedules_searched_on_more_calls_apart():
    from figures import _schedule_label
    a = _schedule_label({"sparsity": 0.93, "calibration_calls": 64})
    b = _schedule_label({"sparsity": 0.93, "calibration_calls": 256})
    assert a != b and "256 calls" in b and "rho=0.93" in a


def test_runs_of_other_policies_and_validation_seeds_never_pool_with_the_bundled_test_runs():
    from common.stats import policy_of

    run = {"task": "lift", "checkpoint": "checkpoints/lift_dpt", "provenance": {"seeds": [100000, 100001]}}
    assert policy_of(run) == "lift"
    assert policy_of({**run, "checkpoint": "checkpoints/lift_mh_dpt"}) == "lift (lift_mh_dpt)"
    assert policy_of({**run, "provenance": {"seeds": [400000]}}) == "lift, validation"


def test_table7_rows_pool_test_seeds_per_policy_and_skip_validation(tmp_path):
    import tables
    from helpers import write_success_run

    def write(method, successes, seed, macs_pruner=0.0, pruner=None):
        write_success_run(tmp_path, method, successes, first_seed=seed, pruner_metadata=pruner,
                          tts={"last_call": {"macs_dense": 2e9, "macs_pruner": macs_pruner}})

    assert "No policy" in tables.table7(tmp_path)
    write("dense", [1, 1, 1, 0], 100000)
    write("pruner:lift-lift_mh_dpt_reference_rollout_0.93", [1, 0, 1, 0], 100000, macs_pruner=3e9)
    write("pruner:lift-lift_mh_dpt_reference_rollout_0.93", [1, 1], 400000)  # validation: not pooled
    write("file:lift-lift_mh_dpt_steps_0.93", [1, 1, 1, 1], 100000)
    text = tables.table7(tmp_path)
    header, _, *rows = text.strip().splitlines()
    assert header == "| row | lift (lift_mh_dpt) |"
    row = {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in rows}
    assert row["dense"] == "0.75 (4)"
    assert row["rollout only (pruner, scratch)"].startswith("0.50 (4); -0.250 (")
    assert row["rollout only (pruner, scratch)"].endswith("; pruner MACs 1.50x a dense call's")
    assert row["searched static steps"].startswith("1.00 (4); +0.250 (")
    assert "pruner MACs" not in row["searched static steps"]
    assert row["omni (pruner, scratch)"] == "-"
    # a pruner evaluated while its training went on says which epoch ran; seeds with other weights are flagged
    in_progress = {"weights_sha256": "a", "epochs": 20, "epochs_done": 17, "best_epoch": {"epoch": 12}}
    omni = "pruner:lift-lift_mh_dpt_reference_forward-timestep-rollout_0.93"
    write(omni, [1, 1, 1, 0], 100000, macs_pruner=1e9, pruner=in_progress)
    no_checkpoints = tmp_path / "pruners"  # not the repository's own: its trainings change under it
    no_checkpoints.mkdir()
    cell = lambda: {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in
                    tables.table7(tmp_path, pruners=no_checkpoints).strip().splitlines()[2:]}["omni (pruner, scratch)"]
    assert cell().endswith("training in progress: its best epoch (12) of the first 17 of 20")
    write(omni, [1, 1], 100050, macs_pruner=1e9, pruner=dict(in_progress, weights_sha256="b"))
    assert "the seeds ran different pruner weights" in cell()


def test_table7_flags_results_of_weights_the_checkpoint_no_longer_holds(tmp_path):
    """A training that goes on after its best epoch was evaluated may replace the weights under the
    pruner's name: the cell says the checkpoint holds another epoch, until the results run it."""
    import tables
    from common import file_sha256
    from helpers import write_coverage_run

    results, pruners = tmp_path / "results", tmp_path / "pruners"
    results.mkdir(), pruners.mkdir()
    name = "pusht-pusht_mh_dpt_17k_reference_forward-timestep-rollout_0.93"
    weights = pruners / f"{name}.safetensors"
    weights.write_bytes(b"epoch 12")
    (pruners / f"{name}.json").write_text(json.dumps({"metadata": {"best_epoch": {"epoch": 18}, "epochs": 20,
                                                                    "history": [{}] * 20}}))
    ran = {"weights_sha256": file_sha256(weights), "epochs": 20, "epochs_done": 17, "best_epoch": {"epoch": 12}}
    write_coverage_run(results, "dense", [0.5, 0.6])
    write_coverage_run(results, f"pruner:{name}", [0.1, 0.2], pruner_metadata=ran,
                       tts={"last_call": {"macs_dense": 2e9, "macs_pruner": 1e9}})

    def cell() -> str:
        rows = tables.table7(results, pruners=pruners).strip().splitlines()[2:]
        return {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in rows}["omni (pruner, scratch)"]
    assert cell().endswith("training in progress: its best epoch (12) of the first 17 of 20")
    weights.write_bytes(b"epoch 18")
    assert cell().endswith("**the checkpoint now holds other weights (its best epoch 18 after 20 of 20 epochs), not evaluated yet**")


def test_table7_shows_push_t_coverage_and_starts_with_the_static_direction_rows(tmp_path):
    """A Push-T policy rarely succeeds: its cells give mean best coverage and the paired coverage
    difference to dense; the static rows alone (no pruner trained yet) already make a column."""
    import tables
    from helpers import write_coverage_run

    write_coverage_run(tmp_path, "dense", [0.5, 0.6, 0.7])
    write_coverage_run(tmp_path, "uniform:0.93:rollout", [0.1, 0.2, 0.3])
    assert "No policy" in tables.table7(tmp_path)  # not yet a Table 7 run
    write_coverage_run(tmp_path, "rotating:0.93:rollout", [0.4, 0.6, 0.5])
    header, _, *rows = tables.table7(tmp_path).strip().splitlines()
    assert header == "| row | pusht (pusht_mh_dpt_17k) |"
    row = {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in rows}
    assert row["dense"] == "coverage 0.600 (3)"
    assert row["rollout only (uniform static: slots from the episode's first call)"] == \
        "coverage 0.200 (3); -0.400 (-0.400, -0.400)"
    assert row["rollout only (rotating static: slots refreshed)"].startswith("coverage 0.500 (3); -0.100 (")


def test_paired_score_difference_uses_shared_episodes_and_a_t_interval():
    from common.stats import paired_score_difference

    def scored(values, first=0):
        return [{"episodes": [{"seed": first + i, "max_coverage": v} for i, v in enumerate(values)]}]

    assert paired_score_difference(scored([0.5]), scored([0.2])) is None  # one shared episode: no interval
    mean, lo, hi, n = paired_score_difference(scored([0.5, 0.7, 0.9, 0.4]), scored([0.3, 0.7, 0.5, 0.2, 0.9]))
    assert n == 4 and mean == pytest.approx(0.2)  # the fifth episode ran only once: left out
    assert lo == pytest.approx(0.2 - 1.96 * 0.16329931618554525 / 2) and hi == pytest.approx(0.2 + 1.96 * 0.16329931618554525 / 2)


def test_coverage_table_pairs_each_sampler_with_dense_of_the_same_policy(tmp_path):
    import tables
    from helpers import write_coverage_run

    def write(method, cov, steps):
        write_coverage_run(tmp_path, method, cov, "checkpoints/pusht_mh_dpt", 400000, batch=2,
                           tts={"calls": 5, "num_branches": 24, "decision_counts": {"compute": steps * 5 * 2 * 24}})

    assert "No Push-T runs" in tables.coverage_table(tmp_path)
    write("ddim:3", [0.5, 0.4, 0.6], 3)
    write("uniform:0.93:timestep", [0.6, 0.5, 0.7], 7)
    write("dense", [0.96, 0.5, 0.7], 100)
    rows = tables.coverage_table(tmp_path).strip().splitlines()[2:]
    assert rows[0].startswith("| pusht (pusht_mh_dpt), validation | `dense` | 100.0 | 0.33 (3) | 0.720 | - |")
    assert "| `uniform:0.93:timestep` | 7.0 | 0.00 (3) | 0.600 | -0.120 (" in rows[1]  # by computed steps
    assert rows[1].endswith("| `ddim:3`: +0.100 (+0.100, +0.100) |")  # the best sampler computing <= 7 steps
    assert "| `ddim:3` | 3.0 | 0.00 (3) | 0.500 | -0.220 (" in rows[2] and rows[2].endswith("; 3) | - |")


def test_image_tables_show_ddim_with_the_same_compute_and_macs_against_dense_50(tmp_path):
    import tables

    def run(method, steps, realised, fid, plan="dense (untouched model)"):
        (tmp_path / f"digits_{method.replace(':', '-')}.json").write_text(json.dumps(
            {"method": method, "steps": steps, "fid": fid, "num_samples": 2000, "macs_dense_per_image": 100.0 * steps,
             "macs_realised_per_image": realised, "macs_pruner_per_image": 0.0, "macs_ratio_with_pruner": 1.0,
             "plan": plan, "sparsity": 0.0, "sfid": fid, "s_per_image": 0.1,
             "provenance": {"git_sha": "0" * 40}}))

    run("dense", 50, 5000.0, 40.0)
    run("ddim:10", 10, 1000.0, 55.0)  # its own dense is 10 steps: the MACs column must still say 5x
    run("pruner:p@0.8", 50, 1000.0, 45.0, plan="pruner[budget:0.8](forward,timestep)")
    (tmp_path / "latency.json").write_text(json.dumps({"rows": [
        {"batch": 16, "dense_ms": 100.0, "methods": {"ddim:10": {"speedup": 4.9}}}]}))
    table = tables.headline_image(tmp_path)
    assert "| `ddim:10` | 55.00 | 5.00x | 4.90x |" in table and table.index("`dense`") < table.index("`ddim:10`")
    full = tables.image_table(tmp_path)
    assert "| `ddim:10` | dense (untouched model), 10 sampler steps | 0.000 | 5.00x | 55.00 | +37.5% |" in full
    assert "| `pruner:p@0.8` | pruner\\[budget:0.8](forward,timestep) |" in full  # not a Markdown link


def test_pruner_training_table_shows_the_curve_of_a_training_in_progress(tmp_path):
    import tables

    assert tables.pruner_training_table(tmp_path).startswith("No reference-recipe pruner")
    hist = [{"epoch": 0, "val_l1": 0.11, "val_sparsity": 0.93},
            {"epoch": 1, "train_l1": 0.2, "train_sparsity": 0.5, "val_l1": 0.09, "val_sparsity": 0.61,
             "val_reuse_timestep": 0.5, "val_reuse_rollout": 0.11}]
    (tmp_path / "pusht_reference_prior_0.93.json").write_text(json.dumps(
        {"metadata": {"history": hist, "best_epoch": hist[1], "epochs": 20, "val_l1_dense": 0.05, "paired": True}}))
    stretches = [{"epoch": 0, "groups": 0, "precision": "float32", "device": "cuda: NVIDIA H200"},
                 {"epoch": 0, "groups": 2, "precision": "float32", "device": "cpu: AMD EPYC"}]
    (tmp_path / "pusht_reference_omni_0.93.json").write_text(json.dumps(
        {"metadata": {"history": hist, "best_epoch": hist[0], "epochs": 20, "precision_log": stretches}}))
    (tmp_path / "lift_tts_0.93.json").write_text("{}")  # not a reference-recipe pruner: not read
    table = tables.pruner_training_table(tmp_path)
    assert ("| `pusht_reference_prior_0.93` | 1 of 20 | - | dense, same noise | 1: 0.0900, 0.610 | - / 0.50 / 0.11 | "
            "0.0500 | 0.93 0.61 | "
            "0.110 0.090 | - 0.50 |") in table
    assert ("| `pusht_reference_omni_0.93` | 1 of 20 | cuda: NVIDIA H200, float32, from epoch 1 group 1; "
            "cpu: AMD EPYC, float32, from epoch 1 group 3 | dense, another draw | 0: 0.1100, 0.930 |") in table


def test_visuomotor_table_joins_success_with_latency_and_the_encoder_share(tmp_path):
    import tables

    def write(method, successes, obs_type="image", task="lift"):
        eps = [{"seed": 100000 + i, "success": bool(x)} for i, x in enumerate(successes)]
        doc = {"task": task, "checkpoint": f"checkpoints/{task}_image_dpt", "method": method, "obs_type": obs_type,
               "episodes_requested": len(eps), "episodes_done": len(eps), "success_rate": sum(successes) / len(eps),
               "provenance": {"seeds": [e["seed"] for e in eps]}, "episodes": eps}
        (tmp_path / f"{task}_{obs_type}_{method.replace(':', '-')}.json").write_text(json.dumps(doc))

    write("dense", [1, 1, 1, 0])
    write("uniform:0.93:timestep", [1, 0, 1, 0])
    write("ddim:7", [1, 1], obs_type="low_dim")  # another policy's row: not on the page
    row = {"batch": 1, "dense_ms": {"median": 100.0}, "accelerated_ms": {"median": 40.0}, "speedup": 2.5,
           "sparsity": 0.93, "macs_per_call": {"dense": 100.0, "realised_with_pruner": 10.0},
           "timing_median_ms": {"image_encoder": 19.0, "total": 40.0}, "image_encoder_ms": {"dense": 20.0, "accelerated": 19.0}}
    (tmp_path / "latency_lift-lift_image_dpt_uniform.json").write_text(json.dumps(
        {"task": "lift", "checkpoint": "checkpoints/lift_image_dpt", "method": "uniform:0.93:timestep", "rows": [row]}))
    _, _, *rows = tables.visuomotor_table(tmp_path).strip().splitlines()
    assert len(rows) == 2 and rows[0].startswith("| lift (lift_image_dpt) | `dense` | 0.75 (4) | - | - |")
    cells = rows[1].split(" | ")
    assert cells[2] == "0.50 (4)" and cells[3].startswith("-0.250 (")
    assert cells[5:8] == ["100.0", "40.0", "**2.50x**"]
    assert cells[8] == "20.0 / 19.0 (20% / 48%)"
    assert cells[9] == "3.57x, 70%"  # 100 / (20 + 0.1 * 80)
    # GPU timings (their own folder) join the same success runs; a run with the overlap off is its own row
    gpu = tmp_path / "gpu"
    gpu.mkdir()
    for overlap, ms in (("auto", 10.0), ("off", 12.0)):
        timed = dict(row, accelerated_ms={"median": ms}, speedup=100.0 / ms)
        (gpu / f"latency_lift-lift_image_dpt_uniform_{overlap}.json").write_text(json.dumps(
            {"task": "lift", "checkpoint": "checkpoints/lift_image_dpt", "method": "uniform:0.93:timestep",
             "parallel": overlap, "rows": [timed]}))
    write("dense", [1], task="can")  # a policy never timed on the GPU
    assert "| can (can_image_dpt) | `dense` |" in tables.visuomotor_table(tmp_path)
    _, _, *rows = tables.visuomotor_table(tmp_path, gpu).strip().splitlines()
    assert [r.split(" | ")[1:3] + r.split(" | ")[6:8] for r in rows[1:]] == [
        ["`uniform:0.93:timestep`", "0.50 (4)", "10.0", "**10.00x**"],
        ["`uniform:0.93:timestep (--parallel off)`", "-", "12.0", "**8.33x**"]]
    assert "parallel off" not in tables.visuomotor_table(tmp_path)  # the CPU table keeps its own rows


def _lift_frontier(folder, successes: dict, speeds: dict) -> None:
    """Test-seed runs of the bundled Lift policy (method -> per-episode successes) and one frontier
    latency file (method -> (batch-1 speed-up, computed steps); at batch 28 the speed-up is 1/28 higher)."""
    for method, wins in successes.items():
        eps = [{"seed": 100000 + i, "success": bool(x)} for i, x in enumerate(wins)]
        doc = {"task": "lift", "checkpoint": "checkpoints/lift_dpt", "method": method, "episodes_requested": len(eps),
               "episodes_done": len(eps), "success_rate": sum(wins) / len(eps),
               "provenance": {"seeds": [e["seed"] for e in eps]}, "episodes": eps,
               "tts": {"last_call": {"macs_dense": 100.0, "macs_realised": 10.0}}}
        (folder / f"lift_{method.replace(':', '-')}.json").write_text(json.dumps(doc))
    rows = [{"method": m, "batch": b, "latency_ms": 100 / (s + b / 28 - 1 / 28), "dense_ms": 100.0,
             "speedup": s + b / 28 - 1 / 28, "computed_steps": k} for b in (1, 28) for m, (s, k) in speeds.items()]
    (folder / "frontier_latency_lift.json").write_text(json.dumps(
        {"task": "lift", "checkpoint": "checkpoints/lift_dpt", "policy": "lift", "rows": rows}))


def test_robot_headline_takes_frontier_speed_ups_and_shows_the_sampler_each_sparse_row_is_held_against(tmp_path):
    import tables

    _lift_frontier(tmp_path, {"dense": [1] * 20, "ddim:7": [1] * 20, "ddim:3:trailing": [1] * 20, "ddim:2": [1] * 20,
                              "file:lift_steps_0.93": [1] * 19 + [0]},
                   {"ddim:7": (14.0, 7), "ddim:3:trailing": (30.0, 3), "ddim:2": (45.0, 2),
                    "file:lift_steps_0.93": (10.0 + 1 / 28, 7)})
    lines = tables.headline_robot(tmp_path).strip().splitlines()[2:]
    assert [line.split(" | ")[1] for line in lines] == ["`dense`", "`ddim:7`", "`ddim:2`", "`file:lift_steps_0.93`"]
    steps = lines[3].split(" | ")
    assert steps[4] == "10.04x / 11.00x"  # the frontier's batch-1 and batch-28 speed-ups
    assert steps[6].startswith("`ddim:2`: -0.050 (")  # the most successful sampler at least as fast


def test_sampler_families_table_pairs_each_sparse_method_with_every_family_as_fast(tmp_path):
    import tables

    _lift_frontier(tmp_path, {"dense": [1] * 30, "ddim:7": [1] * 30, "ddim:2": [0] * 30, "dpm:3": [0] * 30,
                              "dpm:12": [1] * 30, "uniform:0.9:timestep": [1] * 29 + [0]},
                   {"ddim:7": (14.0, 7), "ddim:2": (45.0, 2), "dpm:3": (30.0, 3), "dpm:12": (8.0, 12),
                    "uniform:0.9:timestep": (10.0, 10)})
    lines = tables.sampler_families_table(tmp_path).strip().splitlines()
    assert "ddim as fast" in lines[0] and "dpm as fast" in lines[0] and "ddpm" not in lines[0]  # only families run
    cells = lines[2].split(" | ")
    assert cells[1:3] == ["`uniform:0.9:timestep`", "10.00x"]
    assert cells[4].startswith("`ddim:7`: -0.033 (") and "wins" not in cells[4]  # the best DDIM as fast
    assert cells[5].startswith("`dpm:3`: +0.967 (") and cells[5].endswith("**wins** |")  # DPM-12 is slower: not a rival
    assert len(lines) == 3  # samplers are rivals, not rows


def test_training_curves_label_each_reference_pruner_and_take_the_searched_steps_from_the_prior_run(tmp_path):
    from figures import training_curves_of

    def write(name, hist, **meta):
        (tmp_path / f"{name}.json").write_text(json.dumps({"metadata": {"history": hist, "sparsity": 0.93, **meta}}))
    write("pusht-p_reference_prior_0.93", [{"epoch": 0, "val_l1": 0.11}, {"epoch": 1, "val_l1": 0.15}])
    write("pusht-p_reference_forward-timestep-rollout_0.93", [{"epoch": 1, "val_l1": 0.2}, {"epoch": 2, "val_l1": 0.1}],
          val_l1_dense=0.05)
    write("pusht-p_reference_timestep_0.93", [{"epoch": 1, "val_l1": 0.3}])
    write("pusht-p_reference_rollout_0.93", [])
    # read after the omni run: its dense L1 (0, same noise) is not the floor
    write("pusht-p_reference_paired_forward-timestep-rollout_0.93", [{"epoch": 1, "val_l1": 0.25}], val_l1_dense=0.0,
          paired=True)
    write("pusht-other_reference_rollout_0.93", [{"epoch": 1, "val_l1": 9.0}])  # another policy: not read
    curves, searched, meta = training_curves_of(tmp_path, "pusht-p")
    assert searched == 0.11 and meta["sparsity"] == 0.93 and meta["val_l1_dense"] == 0.05
    assert {k: [h["epoch"] for h in v] for k, v in curves.items()} == {
        "omni, from the searched prior": [1], "omni, from scratch": [1, 2], "timestep only, from scratch": [1],
        "rollout only, from scratch": [], "omni, from scratch, paired noise": [1]}
    assert training_curves_of(tmp_path, "lift")[:2] == ({}, None)


def test_sample_spread_table_lists_every_method_of_a_run(tmp_path):
    import tables

    assert tables.sample_spread_table(tmp_path).startswith("No sample-spread run")
    sha = {"provenance": {"git_sha": "abcdef0123456"}}
    doc = {"task": "pusht", "checkpoint": "checkpoints/pusht_mh_dpt_17k",
           "methods": {"dense": {"calls": 10, "draws": 4, "spread": 0.1, "l1_same_draw": 0.0, "l1_other_draw": 0.2, **sha},
                       "dpm:7": {"calls": 10, "draws": 4, "spread": 0.05, "l1_same_draw": 0.1, "l1_other_draw": 0.15,
                                 **sha}}}
    (tmp_path / "sample_spread_pusht-pusht_mh_dpt_17k.json").write_text(json.dumps(doc))
    rows = tables.sample_spread_table(tmp_path).strip().splitlines()[2:]
    assert rows == ["| pusht (pusht_mh_dpt_17k) | `dense` | 10 x 4 | 0.1000 | 0.0000 | 0.2000 | `abcdef0123` |",
                    "| pusht (pusht_mh_dpt_17k) | `dpm:7` | 10 x 4 | 0.0500 | 0.1000 | 0.1500 | `abcdef0123` |"]


def test_table7_vs_steps_pairs_each_sparse_row_with_the_searched_steps_on_shared_episodes(tmp_path):
    """The second Table 7 view: each sparse row minus the searched static steps on the same episodes,
    with the discordant counts in the order only-the-steps / only-this-row."""
    import tables
    from helpers import write_coverage_run, write_success_run

    def write(method, successes):
        write_success_run(tmp_path, method, successes)

    prior = "pruner:lift-lift_mh_dpt_reference_prior_0.93"
    write("dense", [1, 1, 1, 1, 1])
    write(prior, [1, 0, 0, 1, 1])
    assert "No Table 7 policy" in tables.table7_vs_steps(tmp_path)  # no searched steps to pair with
    write("file:lift-lift_mh_dpt_steps_0.93", [1, 1, 1, 0, 1])
    header, _, *rows = tables.table7_vs_steps(tmp_path).strip().splitlines()
    assert header == "| row | lift (lift_mh_dpt) |"
    row = {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in rows}
    assert "dense" not in row and "searched static steps" not in row and "DDIM-7 (leading)" not in row
    assert row["omni (pruner, from the searched prior)"].startswith("-0.200 (")
    assert row["omni (pruner, from the searched prior)"].endswith(" on 5; 2 / 1, p = 1")
    assert row["omni (pruner, scratch)"] == "-"
    coverage = tmp_path / "pusht"
    coverage.mkdir()
    write_coverage_run(coverage, "dense", [0.5, 0.6, 0.7])
    write_coverage_run(coverage, "rotating:0.93:rollout", [0.2, 0.3, 0.5])
    write_coverage_run(coverage, "file:pusht-pusht_mh_dpt_17k_steps_0.93", [0.4, 0.5, 0.6])
    rows = tables.table7_vs_steps(coverage).strip().splitlines()[2:]
    cell = {r.split(" | ")[0][2:]: r.split(" | ")[1].rstrip(" |") for r in rows}["rollout only (rotating static: slots refreshed)"]
    assert cell.startswith("-0.167 (")
