"""Collect result JSONs into markdown tables (no number is typed by hand).

    python eval/tables.py

Fills the marked blocks (``<!-- NAME-table:begin (eval/tables.py) -->`` ... ``<!-- NAME-table:end -->``)
of docs/results/robot.md, docs/results/image.md and the README's headline tables from the JSON files
in results/robot/ and results/image/, and renders the image sample grids.
"""
from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path
from typing import Optional, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, file_sha256, write_atomic  # noqa: E402
from common.stats import paired_score_difference, paired_success_difference, policy_of, pooled  # noqa: E402
from common import frontier  # noqa: E402
from robot_suite.tasks import TASKS  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402


def complete_runs(folder: Path, keep=lambda r: "success_rate" in r) -> dict[tuple[str, str], list[dict]]:
    """Finished result runs in ``folder`` that ``keep`` accepts, grouped by (policy, method)."""
    runs: dict[tuple[str, str], list[dict]] = {}
    for path in sorted(folder.glob("*.json")):
        r = json.loads(path.read_text())
        if keep(r) and r.get("episodes_done") is not None and r["episodes_done"] == r.get("episodes_requested"):
            runs.setdefault((policy_of(r), r["method"]), []).append(r)
    return runs


def robot_table(folder: Path) -> str:
    rows = ["| task | method | success | episodes | seeds | batch | call latency median / p90 (ms) | calls/s | actions/s per env | sparsity | MACs ratio dense / (realised + pruner) | git SHA |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("*.json")):
        r = json.loads(path.read_text())
        if "success_rate" not in r:
            continue
        lc = r.get("tts", {}).get("last_call", {})
        realised = lc.get("macs_realised_with_pruner", lc.get("macs_realised"))
        ratio = lc["macs_dense"] / realised if realised else float("nan")
        info = r.get("tts", {})
        sparsity = info.get("sparsity_non_dense_calls", info.get("sparsity_all_calls", 0))
        seeds = r["provenance"]["seeds"]
        rows.append(
            f"| {policy_of(r)} | `{r['method']}` | {r['success_rate']:.2f} | {r['episodes_done']}/{r['episodes_requested']} | "
            f"{seeds[0]}..{seeds[-1]} | {r['batch']} | {r['latency_ms']['median']:.1f} / {r['latency_ms']['p90']:.1f} | "
            f"{r['calls_per_s']:.2f} | {r['actions_per_s_per_env']:.1f} | {sparsity:.3f} | "
            f"{ratio:.2f} | `{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def summary_table(folder: Path) -> str:
    """Success per (task, method): mean +- std over evaluation seeds (complete runs only)."""
    runs = complete_runs(folder)
    rows = ["| task | method | success mean | std | evaluation seeds (first test seed of each run) | sparsity "
            "| vs dense on the same episodes: difference (95% CI), episodes only dense / only this method solved, "
            "sign test |",
            "|---|---|---|---|---|---|---|"]
    for (task, method), rs in sorted(runs.items(), key=lambda kv: (kv[0][0], -_mean([r["success_rate"] for r in kv[1]]))):
        sr = [r["success_rate"] for r in rs]
        info = rs[0].get("tts", {})
        sparsity = info.get("sparsity_non_dense_calls", info.get("sparsity_all_calls", 0))
        std = f"{(sum((x - _mean(sr)) ** 2 for x in sr) / (len(sr) - 1)) ** 0.5:.2f}" if len(sr) > 1 else "-"
        first = ", ".join(str(r["provenance"]["seeds"][0]) for r in rs)
        paired = "-" if method == "dense" else paired_success_difference(rs, runs.get((task, "dense"), []))
        rows.append(f"| {task} | `{method}` | {_mean(sr):.2f} | {std} | {len(rs)}: {first} | {sparsity:.3f} | {paired} |")
    return "\n".join(rows) + "\n"


FEW_STEP = frontier.FEW_STEP


def _few_step_key(method: str) -> tuple:
    """dense first, then DDIM (leading), DDIM trailing, DPM-Solver++, stochastic DDPM, each by number of steps."""
    if method == "dense":
        return (0, "", 0)
    family, k, spacing = FEW_STEP.match(method).groups()
    return ({"ddim": 1, "dpm": 2, "ddpm": 3}[family], spacing or "", int(k))


def steps_table(folder: Path) -> str:
    """Does the number of denoising steps matter: success of dense DDPM-100 and the few-step samplers
    (DDIM-k, DDIM-k with trailing timesteps, DPM-Solver++-k, DDPM-k) per policy and split (complete runs;
    the cell also gives the episodes it pools), and dense minus the best 3-step sampler."""
    runs = complete_runs(folder, lambda r: "success_rate" in r
                         and (r["method"] == "dense" or FEW_STEP.match(r["method"]) is not None))
    methods = sorted({m for _, m in runs}, key=_few_step_key)
    rows = ["| policy | " + " | ".join(f"`{m}`" for m in methods) + " | dense - best 3-step |",
            "|---|" + "---|" * (len(methods) + 1)]

    def pooled_rate(policy: str, m: str):
        rs = runs.get((policy, m))
        return pooled(rs) if rs else (None, 0)

    for policy in sorted({p for p, _ in runs}):
        cells = []
        for m in methods:
            rate, n = pooled_rate(policy, m)
            cells.append("-" if rate is None else f"{rate:.2f} ({n})")
        dense, _ = pooled_rate(policy, "dense")
        three = [pooled_rate(policy, m)[0] for m in methods if m != "dense" and _few_step_key(m)[2] == 3]
        three = [x for x in three if x is not None]
        gap = f"{dense - max(three):+.2f}" if dense is not None and three else "-"
        rows.append(f"| {policy} | " + " | ".join(cells) + f" | {gap} |")
    rows += ["", "Median env steps of a successful episode (how fast each sampler's policy solves the task):", "",
             "| policy (horizon) | " + " | ".join(f"`{m}`" for m in methods) + " |", "|---|" + "---|" * len(methods)]
    for policy in sorted({p for p, _ in runs}):
        cells = []
        for m in methods:
            wins = [e["env_steps"] for r in runs.get((policy, m), []) for e in r["episodes"] if e["success"]]
            cells.append(f"{statistics.median(wins):.0f}" if wins else "-")
        task = next(r["task"] for (p, _), rs in runs.items() if p == policy for r in rs)
        rows.append(f"| {policy} ({TASKS[task].horizon}) | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def operators_table(folder: Path) -> str:
    """The mixed-quality operators of every task with MH-style data (results/experts/<task>_mh.json)
    and how multimodal the data is (<task>_mh_modes.json, eval/demo_modes.py)."""
    rows = ["| task | operator | quality | speed | grasp yaw (deg) | approach via (m) | miss rate | noise "
            "| success (seeds) | mean demo length | hand turn before grasp (deg, mean / std) |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("*_mh.json")):
        r = json.loads(path.read_text())
        if r["task"] == "pusht":
            continue  # its operators differ in other ways: push_operators_table
        modes_path = folder / f"{r['task']}_mh_modes.json"
        modes = json.loads(modes_path.read_text())["operators"] if modes_path.exists() else {}
        for op in r["operators"]:
            prm = op["params"]
            yaw = "any" if prm["yaw"] is None else f"{math.degrees(prm['yaw']):.0f}"
            turn = modes.get(op["operator"], {}).get("hand_turn_before_grasp_deg")
            turn = f"{turn['mean']:.0f} / {turn['std']:.0f}" if turn else "-"
            rows.append(f"| {r['task']} | {op['operator']} | {op['quality']} | {prm['speed']:g} | {yaw} | "
                        f"{tuple(prm['approach'])} | {prm['miss']:g} | {prm['noise']:g} | {op['success_rate']:.2f} "
                        f"({op['attempts']}) | {op['mean_demo_length']:.0f} | {turn} |")
    rows += ["", "| task | data | neighbours' action std | pairs of neighbours' commands > 90 deg apart |",
             "|---|---|---|---|"]
    for path in sorted(folder.glob("*_mh_modes.json")):
        r = json.loads(path.read_text())
        for name, v in r["neighbour_action_spread"].items():
            rows.append(f"| {r['task']} | {name} | {v['mean_action_std']:.3f} | {100 * v['opposed_pair_fraction']:.1f}% |")
    return "\n".join(rows) + "\n"


def computed_steps(r: dict) -> float:
    """Denoiser steps a run computed per sample and call: its branch computations over calls x batch x
    branches (a 93% plan on DDPM-100 and DDIM-7 both compute 7)."""
    t = r.get("tts") or {}
    n = t.get("calls", 0) * r["batch"] * t.get("num_branches", 0)
    return t.get("decision_counts", {}).get("compute", 0) / n if n else float("nan")


def coverage_table(folder: Path) -> str:
    """Push-T's own score next to success: the mean best goal coverage per episode (Diffusion Policy
    reports it) of every method run on a Push-T policy, by computed denoiser steps per call, with the
    paired difference to dense on the same episodes (mean and 95% t-interval)."""
    runs = complete_runs(folder, lambda r: r.get("mean_max_coverage") is not None)
    if not runs:
        return "No Push-T runs yet (recipes/pusht_testbed.sh).\n"
    rows = ["| policy | method | computed steps per call | success | mean best coverage | vs dense, paired "
            "(95% CI, episodes) | vs the best fewer-step sampler computing no more, paired |", "|---|---|---|---|---|---|---|"]
    order = {k: (k[0], -computed_steps(v[0]), k[1]) for k, v in runs.items()}

    def coverage(key):
        return pooled(runs[key], "mean_max_coverage")[0]

    def vs_best_sampler(policy: str, method: str) -> str:
        if method == "dense" or FEW_STEP.match(method):
            return "-"
        budget = computed_steps(runs[(policy, method)][0]) + 1e-6
        samplers = [k for k in runs if k[0] == policy and FEW_STEP.match(k[1]) and computed_steps(runs[k][0]) <= budget]
        if not samplers:
            return "-"
        best = max(samplers, key=coverage)
        d = paired_score_difference(runs[(policy, method)], runs[best])
        return "-" if d is None else f"`{best[1]}`: {d[0]:+.3f} ({d[1]:+.3f}, {d[2]:+.3f})"

    for (policy, method) in sorted(runs, key=order.get):
        rs = runs[(policy, method)]
        succ, n = pooled(rs)
        cov = coverage((policy, method))
        diff = None if method == "dense" else paired_score_difference(rs, runs.get((policy, "dense"), []))
        paired = "-" if diff is None else f"{diff[0]:+.3f} ({diff[1]:+.3f}, {diff[2]:+.3f}; {diff[3]})"
        rows.append(f"| {policy} | `{method}` | {computed_steps(rs[0]):.1f} | {succ:.2f} ({n}) | {cov:.3f} | {paired} "
                    f"| {vs_best_sampler(policy, method)} |")
    return "\n".join(rows) + "\n"


def push_operators_table(folder: Path) -> str:
    """Push-T's scripted operators (results/experts/pusht_mh.json): which way round the block each
    prefers, push length, walking speed, hesitation, recorded noise, success and demo length."""
    path = folder / "pusht_mh.json"
    if not path.exists():
        return "No Push-T data recorded yet (eval/collect_demos.py --task pusht --mix mh).\n"
    rows = ["| operator | quality | route round the block (how often) | push length | speed | pauses per step "
            "| noise (px) | success (seeds) | mean demo length |", "|---|---|---|---|---|---|---|---|---|"]
    for op in json.loads(path.read_text())["operators"]:
        prm = op["params"]
        route = {1: "counter-clockwise", -1: "clockwise", None: "shorter way"}[prm["route"]]
        route += f" ({prm['route_bias']:.0%}, else shorter)" if prm["route"] is not None else ""
        rows.append(f"| {op['operator']} | {op['quality']} | {route} | {prm['push']:g}x | {prm['speed']:g} | "
                    f"{prm['hesitate']:g} | {prm['noise']:g} | {op['success_rate']:.2f} ({op['attempts']}) | "
                    f"{op['mean_demo_length']:.0f} |")
    return "\n".join(rows) + "\n"


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def latency_table(folder: Path) -> str:
    rows = ["| task | method | pruner overlap | batch | dense ms | accelerated ms | speed-up | sparsity "
            "| MACs dense / (realised + pruner) | pruner MACs / dense | breakdown ms (median) | git SHA |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("latency_*.json")):
        r = json.loads(path.read_text())
        if r.get("reference", "dense") != "dense":
            continue  # timed against another baseline: reuse_cost_table
        for row in r["rows"]:
            m = row["macs_per_call"]
            brk = ", ".join(f"{k} {v:.1f}" for k, v in row["timing_median_ms"].items())
            rows.append(
                f"| {policy_of(r)} | `{r['method']}` | {r.get('parallel', 'auto')} | {row['batch']} | {row['dense_ms']['median']:.1f} | "
                f"{row['accelerated_ms']['median']:.1f} | **{row['speedup']:.2f}x** | {row['sparsity']:.3f} | "
                f"{m['dense'] / max(m['realised_with_pruner'], 1):.2f} | {m['pruner'] / m['dense']:.4f} | {brk} | "
                f"`{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def reuse_cost_table(folder: Path) -> str:
    """A sparse call against DDIM with the same computed steps (eval/latency.py --reference ddim:matched):
    what the reuse steps, the longer schedule and the pruner add."""
    rows = ["| task | method | batch | DDIM-k (k = computed steps) ms | method ms | method / DDIM-k | "
            "breakdown of the method's call, ms (median) | DDIM-k breakdown | git SHA |",
            "|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("latency_*_vs_*.json")):
        r = json.loads(path.read_text())
        for row in r["rows"]:
            brk = ", ".join(f"{k} {v:.1f}" for k, v in row["timing_median_ms"].items())
            ref = ", ".join(f"{k} {v:.1f}" for k, v in row["reference_timing_median_ms"].items())
            rows.append(f"| {policy_of(r)} | `{r['method']}` | {row['batch']} | {row['reference']}: "
                        f"{row['reference_ms']['median']:.1f} | {row['accelerated_ms']['median']:.1f} | "
                        f"**{row['ratio']:.2f}x** | {brk} | {ref} | `{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


TABLE7_STEPS = "file:{p}_steps_0.93"
TABLE7_ROWS = (("dense", "dense"), ("DDIM-7 (leading)", "ddim:7"), ("DDIM-3 (leading)", "ddim:3"),
               ("DDIM-3 (trailing)", "ddim:3:trailing"), ("DPM-Solver++-3", "dpm:3"), ("DPM-Solver++-7", "dpm:7"),
               ("searched static steps", TABLE7_STEPS),
               ("forward only (uniform static)", "uniform:0.93:forward"),
               ("timestep only (uniform static)", "uniform:0.93:timestep"),
               ("rollout only (uniform static: slots from the episode's first call)", "uniform:0.93:rollout"),
               ("rollout only (rotating static: slots refreshed)", "rotating:0.93:rollout"),
               ("searched steps, rollout at steps 0-49, timestep after", "file:{p}_steps_0.93_rollout_early"),
               ("forward only (pruner, scratch)", "pruner:{p}_reference_forward_0.93"),
               ("timestep only (pruner, scratch)", "pruner:{p}_reference_timestep_0.93"),
               ("rollout only (pruner, scratch)", "pruner:{p}_reference_rollout_0.93"),
               ("omni (pruner, scratch)", "pruner:{p}_reference_forward-timestep-rollout_0.93"),
               ("omni (pruner, from the searched prior)", "pruner:{p}_reference_prior_0.93"),
               ("omni (pruner, scratch, paired noise)", "pruner:{p}_reference_paired_forward-timestep-rollout_0.93"))


def _pruner_cost(rs: list[dict], checkpoint: Path | None = None) -> str:
    """A pruner row's cost next to the policy (the pruner's MACs per call over a dense call's) and, for
    a pruner whose training had not finished, which of its epochs ran. ``checkpoint``: the pruner's
    checkpoint path (without suffix); when its weights are not the ones the results ran, the cell says so."""
    last = (rs[0].get("tts") or {}).get("last_call") or {}
    if not last.get("macs_pruner"):
        return ""
    note = f"; pruner MACs {last['macs_pruner'] / last['macs_dense']:.2f}x a dense call's"
    metas = [r.get("pruner_metadata") or {} for r in rs]
    if len({m.get("weights_sha256") for m in metas}) > 1:
        return note + "; **the seeds ran different pruner weights**"
    m = metas[0]
    if m.get("epochs_done") is not None and m["epochs_done"] < m.get("epochs", 0):
        note += (f"; training in progress: its best epoch ({m['best_epoch']['epoch']}) of the first "
                 f"{m['epochs_done']} of {m['epochs']}")
    weights, meta = checkpoint_pair(checkpoint) if checkpoint is not None else (None, None)
    if weights is not None and weights.is_file() and m.get("weights_sha256") not in (None, file_sha256(weights)):
        now = json.loads(meta.read_text()).get("metadata", {})
        note += (f"; **the checkpoint now holds other weights (its best epoch {now.get('best_epoch', {}).get('epoch', '?')}"
                 f" after {len(now.get('history', []))} of {now.get('epochs', '?')} epochs), not evaluated yet**")
    return note


def _table7_policies(runs: dict) -> list[str]:
    """Policies with Table 7 runs (reference-recipe pruners or the rotating rollout plan), test seeds only."""
    return sorted({pol for pol, m in runs if ("_reference_" in m or m == "rotating:0.93:rollout")
                   and not pol.endswith("validation")})


def _table7_method(pol: str, pattern: str) -> str:
    """A Table 7 row's method name for a policy (``{p}``: the policy's checkpoint slug)."""
    return pattern.format(p=pol.replace(" (", "-").rstrip(")"))


def _paired_cell(rs: list[dict], other: list[dict]) -> str:
    """The paired difference of ``rs`` to ``other`` on their shared episodes: mean best coverage where
    the runs score coverage (t-interval), else success (Newcombe interval, discordant counts, sign test)."""
    if rs[0].get("mean_max_coverage") is not None:
        d = paired_score_difference(rs, other)
        return "-" if d is None else f"{d[0]:+.3f} ({d[1]:+.3f}, {d[2]:+.3f})"
    return paired_success_difference(rs, other)


def table7(folder: Path, pruners: Path = REPO / "checkpoints" / "pruners") -> str:
    """The paper's Table 7 shape at 93% (recipes/table7.sh): per policy with its static direction rows
    or reference-recipe pruners, on the test seeds, the score and the paired difference to dense on the
    same episodes: success, or for Push-T (whose policies rarely succeed) the mean best coverage.
    ``pruners``: where the pruner rows' checkpoints are (a cell flags results of replaced weights)."""
    runs = complete_runs(folder)
    policies = _table7_policies(runs)
    if not policies:
        return "No policy has Table 7 runs yet (recipes/table7.sh).\n"
    rows = ["| row | " + " | ".join(policies) + " |", "|---|" + "---|" * len(policies)]
    for label, pattern in TABLE7_ROWS:
        cells = []
        for pol in policies:
            method = _table7_method(pol, pattern)
            rs, dense = runs.get((pol, method)), runs.get((pol, "dense"), [])
            if not rs:
                cells.append("-")
                continue
            ckpt = pruners / method.removeprefix("pruner:") if method.startswith("pruner:") else None
            coverage = rs[0].get("mean_max_coverage") is not None
            rate, n = pooled(rs, "mean_max_coverage" if coverage else "success_rate")
            paired = "" if pattern == "dense" else "; " + _paired_cell(rs, dense).split(" on ")[0]
            cells.append(("coverage " if coverage else "") + f"{rate:.{3 if coverage else 2}f} ({n}){paired}"
                         + _pruner_cost(rs, ckpt))
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def table7_vs_steps(folder: Path) -> str:
    """Table 7's sparse rows against the searched static steps on the same test episodes: the paired
    difference (success: with the episodes and the discordant counts, only the steps / only this row
    solved, and the sign test; Push-T: mean best coverage)."""
    runs = complete_runs(folder)
    policies = [p for p in _table7_policies(runs) if (p, _table7_method(p, TABLE7_STEPS)) in runs]
    if not policies:
        return "No Table 7 policy has searched-steps runs yet (recipes/table7.sh).\n"
    rows = ["| row | " + " | ".join(policies) + " |", "|---|" + "---|" * len(policies)]
    for label, pattern in TABLE7_ROWS:
        if pattern == TABLE7_STEPS or not pattern.startswith(("pruner:", "file:", "uniform:", "rotating:")):  # sparse rows only
            continue
        cells = []
        for pol in policies:
            rs = runs.get((pol, _table7_method(pol, pattern)))
            cells.append(_paired_cell(rs, runs[(pol, _table7_method(pol, TABLE7_STEPS))]) if rs else "-")
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def _stretches(meta: dict) -> str:
    """Where a training ran: each stretch's device and precision, from the epoch and group it began at
    (trainings recorded before devices were: "-")."""
    log = [s for s in meta.get("precision_log") or [] if "device" in s]
    return "; ".join(f"{s['device']}, {s['precision']}, from epoch {s['epoch'] + 1} group {s['groups'] + 1}"
                     for s in log) or "-"


def pruner_training_table(folder: Path) -> str:
    """The training curves of the reference-recipe pruners (checkpoints/pruners/*_reference_*.json,
    written after every epoch, so a training in progress shows the epochs it has done), with the val L1
    of the untouched policy under the same noise draws (the floor a second noise draw sets; 0 for a
    paired run, whose target is the dense action on the same noise)."""
    rows = ["| pruner | epochs done | where it ran | L1 target | best epoch: val L1, val sparsity | "
            "its reuse by direction (F / T / R) | val L1 of the dense policy | val sparsity per epoch | val L1 per epoch | "
            "train sparsity per epoch |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("*_reference_*.json")):
        meta = json.loads(path.read_text())["metadata"]
        hist, best = meta["history"], meta["best_epoch"]

        def series(key: str, digits: int) -> str:
            return " ".join(f"{h[key]:.{digits}f}" if key in h else "-" for h in hist)
        floor = f"{meta['val_l1_dense']:.4f}" if "val_l1_dense" in meta else "-"
        mix = " / ".join(f"{best[f'val_reuse_{d}']:.2f}" if f"val_reuse_{d}" in best else "-"
                         for d in ("forward", "timestep", "rollout"))
        target = "dense, same noise" if meta.get("paired") else "dense, another draw"
        rows.append(f"| `{path.stem}` | {hist[-1]['epoch']} of {meta['epochs']} | {_stretches(meta)} | {target} | {best['epoch']}: "
                    f"{best['val_l1']:.4f}, {best['val_sparsity']:.3f} | {mix} | {floor} | {series('val_sparsity', 2)} | "
                    f"{series('val_l1', 3)} | {series('train_sparsity', 2)} |")
    if len(rows) == 2:
        return "No reference-recipe pruner has finished an epoch yet (recipes/table7.sh PARTS=pruners).\n"
    return "\n".join(rows) + "\n"


def _timed_policy(doc: dict) -> str:
    """The policy label of a frontier_latency file: the task, with the checkpoint when it is not the bundled one."""
    return doc["task"] if doc["policy"] == doc["task"] else f"{doc['task']} ({Path(doc['checkpoint']).name})"


def _versus_fewer_steps(p, points: list, digits: int, untimed: Sequence[str] = ()) -> str:
    """The last frontier column: a sparse method against the best fewer-step sampler as fast. A win
    over the timed samplers while ``untimed`` ones (run on the test seeds, not timed, with at most as
    many steps) may be as fast is not called a win."""
    if p.family != "sparse":
        return "-"
    vs = frontier.beats_fewer_steps(p, points)
    if vs is None:
        return "no fewer-step sampler as fast"
    cell = f"`{vs[0].method}`: {vs[1]:+.{digits}f} ({vs[2]:+.{digits}f}, {vs[3]:+.{digits}f})"
    if not frontier.is_win(p, vs):
        return cell
    if untimed:
        return cell + f"; no verdict: {', '.join(f'`{m}`' for m in untimed)} not timed here"
    return cell + " **beats it**"


def frontier_table(folder: Path, latency_folder: Optional[Path] = None) -> str:
    """Score (success, or Push-T's mean best coverage) against speed-up over dense per policy and batch
    size (eval/common/frontier.py): every method with test-seed runs and a row in
    frontier_latency_<policy>.json, read from ``latency_folder`` (default ``folder``; ``folder/gpu``:
    the latencies timed on a GPU, with the success runs of ``folder``)."""
    rows = ["| policy | batch | method | computed steps | score (episodes) [95% CI] | speed-up vs dense | "
            "ms per call | on the frontier | sparse: minus the best fewer-step sampler at least as fast (paired 95% CI) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for path in sorted((latency_folder or folder).glob("frontier_latency_*.json")):
        doc = json.loads(path.read_text())
        policy = _timed_policy(doc)
        for batch in sorted({r["batch"] for r in doc["rows"]}):
            points = frontier.frontier_points(folder, policy, batch, latency_folder)
            untimed = frontier.untimed_samplers(folder, policy, points)
            for p in sorted(points, key=lambda q: -q.speedup):
                rivals = [m for m, k in untimed.items() if k <= p.computed_steps]
                versus = _versus_fewer_steps(p, points, 3, rivals)
                steps = "100" if p.method == "dense" else str(p.computed_steps)
                rows.append(f"| {policy} | {batch} | `{p.method}` | {steps} | {p.metric} {p.score:.3f} ({p.episodes}) "
                            f"[{p.interval[0]:.3f}, {p.interval[1]:.3f}] | {p.speedup:.2f}x | {p.latency_ms:.1f} | "
                            f"{'yes' if frontier.on_frontier(p, points) else ''} | {versus} |")
    return "\n".join(rows) + "\n"


def sampler_families_table(folder: Path, batch: int = 1) -> str:
    """Every sparse method of a timed policy at ``batch`` against the best sampler of each fewer-step
    family (DDIM, DPM-Solver++, DDPM, trailing DDIM) at least as fast: the paired difference on the same
    test episodes, so the verdict against each sampler a user might pick is read off, not only against
    the best one (the frontier table's last column)."""
    policies = {}
    for path in sorted(folder.glob("frontier_latency_*.json")):
        doc = json.loads(path.read_text())
        policy = _timed_policy(doc)
        policies[policy] = frontier.frontier_points(folder, policy, batch)
    families = [f for f in frontier.SAMPLER_FAMILIES if any(q.family == f for ps in policies.values() for q in ps)]
    rows = ["| policy | method | speed-up vs dense | score | " + " | ".join(f"minus best {f} as fast (paired 95% CI)"
                                                                  for f in families) + " |",
            "|---|---|---|---|" + "---|" * len(families)]
    for policy, points in policies.items():
        for p in sorted((q for q in points if q.family == "sparse"), key=lambda q: -q.speedup):
            cells = []
            for fam in families:
                vs = frontier.beats_fewer_steps(p, [q for q in points if q.family == fam])
                cells.append("-" if vs is None else
                             f"`{vs[0].method}`: {vs[1]:+.3f} ({vs[2]:+.3f}, {vs[3]:+.3f}){' **wins**' if frontier.is_win(p, vs) else ''}")
            rows.append(f"| {policy} | `{p.method}` | {p.speedup:.2f}x | {p.metric} {p.score:.3f} ({p.episodes}) | "
                        + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def image_frontier_table(folder: Path) -> str:
    """FID against speed-up over dense DDIM-50 per batch size (eval/common/frontier.py): every image run
    with a row in results/image/frontier_latency.json."""
    rows = ["| batch | method | sampler steps | FID [95% CI] | sFID | speed-up vs dense | ms per call | on the frontier | "
            "sparse: FID minus the best fewer-step sampler at least as fast (conservative 95% CI) |",
            "|---|---|---|---|---|---|---|---|---|"]
    latency = folder / "frontier_latency.json"
    if not latency.exists():
        return "\n".join(rows) + "\n"
    for batch in sorted({r["batch"] for r in json.loads(latency.read_text())["rows"]}):
        points = frontier.image_frontier_points(folder, latency, batch)
        for p in sorted(points, key=lambda q: -q.speedup):
            versus = _versus_fewer_steps(p, points, 2)
            sfid = p.runs[0].get("sfid")
            rows.append(f"| {batch} | `{p.method}` | {p.computed_steps} | {p.score:.2f} [{p.interval[0]:.2f}, "
                        f"{p.interval[1]:.2f}] | {'-' if sfid is None else f'{sfid:.2f}'} | {p.speedup:.2f}x | "
                        f"{p.latency_ms:.1f} | {'yes' if frontier.on_frontier(p, points) else ''} | {versus} |")
    return "\n".join(rows) + "\n"


def visuomotor_table(folder: Path, latency_folder: Optional[Path] = None) -> str:
    """Image-observation policies: success per method on the test seeds (paired against dense) and,
    where eval/latency.py timed the method (files in ``latency_folder``, default ``folder``;
    ``folder/gpu``: timed on a GPU), its call latency against dense with the image encoder's share and
    the fraction reached of the ideal speed-up (reused branches free, encoder and computed branches as
    in the dense call). A run with the pruner's overlap forced off is its own row. With a separate
    ``latency_folder`` only the policies timed there are listed."""
    runs = complete_runs(folder, lambda r: r.get("obs_type") == "image")
    timed: dict[tuple[str, str], dict] = {}
    policies = {p for p, _ in runs}
    for path in sorted((latency_folder or folder).glob("latency_*.json")):
        r = json.loads(path.read_text())
        image = policy_of(r) in policies or any("image_encoder_ms" in row for row in r["rows"])
        if r.get("reference", "dense") == "dense" and image:
            overlap = r.get("parallel", "auto")
            timed[(policy_of(r), r["method"] + ("" if overlap == "auto" else f" (--parallel {overlap})"))] = r
    rows = ["| policy | method | success (episodes) | vs dense: difference (95% CI) on the same episodes | batch "
            "| dense ms | method ms | speed-up | image encoder ms: dense / method (share of the call) "
            "| ideal speed-up, reached | breakdown ms (median) |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    listed = set(runs) | set(timed)
    if latency_folder is not None and latency_folder != folder:
        timed_policies = {p for p, _ in timed}
        listed = {k for k in listed if k[0] in timed_policies}
    for key in sorted(listed, key=lambda k: (k[0], k[1] != "dense", k[1])):
        policy, method = key
        rs = runs.get(key, [])
        score = "-" if not rs else "{:.2f} ({})".format(*pooled(rs))
        versus = "-" if not rs or method == "dense" else paired_success_difference(rs, runs.get((policy, "dense"), []))
        latency_rows = timed[key]["rows"] if key in timed else [None]
        for row in latency_rows:
            if row is None:
                rows.append(f"| {policy} | `{method}` | {score} | {versus} | - | - | - | - | - | - | - |")
                continue
            dense_ms, ms = row["dense_ms"]["median"], row["accelerated_ms"]["median"]
            enc = row.get("image_encoder_ms", {})
            enc_d, enc_m = enc.get("dense", float("nan")), enc.get("accelerated", float("nan"))
            m = row["macs_per_call"]
            computed = m["realised_with_pruner"] / m["dense"] if row["sparsity"] > 0 else float("nan")
            ideal = dense_ms / (enc_d + computed * (dense_ms - enc_d))
            ideal_txt = "-" if math.isnan(ideal) else f"{ideal:.2f}x, {row['speedup'] / ideal:.0%}"
            brk = ", ".join(f"{k} {v:.1f}" for k, v in row["timing_median_ms"].items())
            rows.append(f"| {policy} | `{method}` | {score} | {versus} | {row['batch']} | {dense_ms:.1f} | {ms:.1f} | "
                        f"**{row['speedup']:.2f}x** | {enc_d:.1f} / {enc_m:.1f} ({enc_d / dense_ms:.0%} / {enc_m / ms:.0%}) "
                        f"| {ideal_txt} | {brk} |")
    return "\n".join(rows) + "\n"


def agreement_table(folder: Path) -> str:
    """How often a pruner's decisions equal its prior (eval/pruner_agreement.py: agreement_*.json)."""
    rows = ["| task | pruner | prior | exact budget | episodes not trained on | calls identical to the prior | "
            "decisions identical | git SHA |", "|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("agreement_*.json")):
        r = json.loads(path.read_text())
        budget = "argmax" if r["sparsity"] is None else f"{r['sparsity']:g}"
        rows.append(f"| {r['task']} | {Path(r['pruner']).name} | {Path(r['prior']).name} | {budget} | {r['episodes']} | "
                    f"{r['calls_identical']}/{r['calls']} ({100 * r['calls_identical_fraction']:.1f}%) | "
                    f"{100 * r['decisions_identical_fraction']:.2f}% | `{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def headroom_table(folder: Path) -> str:
    """Per-call oracle headroom around a searched schedule (eval/oracle_headroom.py: headroom_*.json)."""
    rows = ["| task | schedule (compute steps) | held-out calls x candidates | action L1: searched | best fixed "
            "| per-call oracle (same noise) | best fixed / oracle, chosen on another noise draw | git SHA |",
            "|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("headroom_*.json")):
        r = json.loads(path.read_text())
        rows.append(f"| {r['task']} | {Path(r['schedule']).name} ({', '.join(map(str, r['compute_steps']))}) | "
                    f"{r['calls']} x {r['candidates']} | {r['searched_error']:.4f} | {r['best_fixed_error']:.4f} | "
                    f"{r['oracle_error']:.4f} ({-100 * r['oracle_gain_over_best_fixed']:+.1f}% vs best fixed) | "
                    f"{r['cross_noise_best_fixed_error']:.4f} / {r['cross_noise_oracle_error']:.4f} "
                    f"({-100 * r['cross_noise_oracle_gain_over_best_fixed']:+.1f}%) | "
                    f"`{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def rollout_age_table(folder: Path) -> str:
    """Age in calls of the reused rollout slots (eval/rollout_age.py: rollout_age_<policy>.json)."""
    rows = ["| policy | method | sparsity | reused rollout slots | mean age (calls) | median | max "
            "| from the previous call | git SHA |", "|---|---|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("rollout_age_*.json")):
        r = json.loads(path.read_text())
        pol = policy_of({"task": r["task"], "checkpoint": r.get("checkpoint", "")})
        for method, m in r["methods"].items():
            if not m["reused_slots"]:
                rows.append(f"| {pol} | `{method}` | {m['sparsity']:.3f} | 0 | - | - | - | - | "
                            f"`{m['provenance']['git_sha'][:10]}` |")
                continue
            rows.append(f"| {pol} | `{method}` | {m['sparsity']:.3f} | {m['reused_slots']} | "
                        f"{m['mean_calls']:.2f} | {m['median_calls']:.0f} | {m['max_calls']} | "
                        f"{100 * m['fraction_previous_call']:.1f}% | `{m['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def sample_spread_table(folder: Path) -> str:
    """Spread of the actions across noise draws and L1 to the dense action on the same / another draw
    (eval/sample_spread.py: sample_spread_<policy>.json)."""
    rows = ["| policy | method | held-out calls x draws | spread across draws | L1 to dense, same draw | "
            "L1 to dense, another draw | git SHA |", "|---|---|---|---|---|---|---|"]
    for path in sorted(folder.glob("sample_spread_*.json")):
        r = json.loads(path.read_text())
        pol = policy_of({"task": r["task"], "checkpoint": r["checkpoint"]})
        for method, m in r["methods"].items():
            rows.append(f"| {pol} | `{method}` | {m['calls']} x {m['draws']} | {m['spread']:.4f} | "
                        f"{m['l1_same_draw']:.4f} | {m['l1_other_draw']:.4f} | `{m['provenance']['git_sha'][:10]}` |")
    if len(rows) == 2:
        return "No sample-spread run yet (eval/sample_spread.py).\n"
    return "\n".join(rows) + "\n"


IMAGE_ORDER = ("dense", "every_n:5:timestep", "taylorseer:5:2", "toca:6@0.8", "duca:6@0.8", "diffusers:fbc@0.8",
               "diffusers:taylorseer:5:2", "file:digits_bac_0.8", "pruner:digits_tts_0.8@0.8",
               "file:digits_bac_0.8+taylor2", "pruner:digits_tts_taylor2_0.8@0.8+taylor2",
               "file:digits_steps_0.8+taylor2", "pruner:digits_tts_steps_0.8@0.8+taylor2")


def image_runs(folder: Path) -> list[dict]:
    """eval/imagenet.py results (digits_*.json), in IMAGE_ORDER, then any other label alphabetically."""
    runs = [json.loads(p.read_text()) for p in sorted(folder.glob("digits_*.json"))]
    rank = {label: i for i, label in enumerate(IMAGE_ORDER)}
    return sorted(runs, key=lambda r: (rank.get(r["method"], len(rank)), r["method"]))


def image_table(folder: Path) -> str:
    """FID/sFID of eval/imagenet.py runs (digits_<row>.json) + wall-clock from eval/image_latency.py."""
    lat_path = folder / "latency.json"
    lat = json.loads(lat_path.read_text()) if lat_path.exists() else None
    lat_rows = {row["batch"]: row for row in lat["rows"]} if lat else {}
    batches = sorted(lat_rows)
    rows = ["| method | plan | decisions reused | MACs speed-up (pruner incl.) | FID | FID vs dense | sFID | "
            + "".join(f"wall-clock speed-up, batch {b} | " for b in batches) + "s/image (FID run) | git SHA |",
            "|---|---|---|---|---|---|---|" + "---|" * len(batches) + "---|---|"]
    runs = image_runs(folder)
    dense = next((r for r in runs if r["method"] == "dense"), None)
    dense_fid = dense.get("fid") if dense else None
    for r in runs:
        name = r["method"]
        rel = f"{100 * (r['fid'] / dense_fid - 1):+.1f}%" if dense_fid and "fid" in r and name != "dense" else "-"
        speed = "".join(
            ("1.00x | " if name == "dense" else
             f"{lat_rows[b]['methods'][name]['speedup']:.2f}x | " if name in lat_rows[b]["methods"] else "- | ")
            for b in batches)
        # a pruner's repr "pruner[budget:0.8](forward,timestep)" would render as a Markdown link
        plan = r["plan"].replace("[", "\\[") + (f" + Taylor forecast O={_forecast_order(r)}" if _forecast_order(r) else "")
        if dense and r["steps"] != dense["steps"]:
            plan += f", {r['steps']} sampler steps"
        rows.append(f"| `{name}` | {plan} | {r['sparsity']:.3f} | {_macs_speedup(r, dense):.2f}x | "
                    f"{r.get('fid', float('nan')):.2f} | {rel} | {r.get('sfid', float('nan')):.2f} | {speed}"
                    f"{r['s_per_image']:.4f} | `{r['provenance']['git_sha'][:10]}` |")
    return "\n".join(rows) + "\n"


def _macs_speedup(r: dict, dense: dict | None) -> float:
    """MACs of the dense run (all of its sampler steps) over those of run ``r``, its pruner included;
    without a dense run, ``r``'s own ratio (against the model dense on ``r``'s sampler steps)."""
    if dense is None:
        return r["macs_ratio_with_pruner"]
    return dense["macs_dense_per_image"] / max(r["macs_realised_per_image"] + r.get("macs_pruner_per_image", 0.0), 1.0)


def _forecast_order(r: dict) -> int:
    """Order of the Taylor forecast of a run (0: plain reuse), from its JSON or its command."""
    if r.get("forecast"):
        return int(r["forecast"])
    if r.get("method_spec", r.get("method", "")).startswith("taylorseer"):
        if r.get("taylor_order"):
            return int(r["taylor_order"])
        cmd = r["provenance"].get("command", "").split()
        return int(cmd[cmd.index("--taylor-order") + 1]) if "--taylor-order" in cmd else 1
    return 0


def sample_grids(folder: Path) -> list[Path]:
    """A 10 x 10 PNG of the first 100 samples of every digits_<row>.npz (column = class), 4x upscaled."""
    import numpy as np
    from PIL import Image

    out = []
    for npz in sorted(folder.glob("digits_*.npz")):
        arr = np.load(npz)["arr_0"][:100]
        n, h, w, c = arr.shape
        side = int(np.ceil(n / 10))
        grid = np.full((side * (h + 1), 10 * (w + 1), c), 255, dtype=np.uint8)
        for i, img in enumerate(arr):
            r, col = divmod(i, 10)
            grid[r * (h + 1):r * (h + 1) + h, col * (w + 1):col * (w + 1) + w] = img
        png = folder / f"grid_{npz.stem[len('digits_'):]}.png"
        Image.fromarray(grid).resize((grid.shape[1] * 4, grid.shape[0] * 4), Image.NEAREST).save(png)
        out.append(png)
    return out


HEADLINE_ROBOT = {"lift": ("dense", "ddim:7", "file:lift_steps_0.93", "pruner:lift_tts_0.93@0.93"),
                  "can": ("dense", "ddim:7", "file:can_steps_0.93_256calls", "pruner:can_tts_0.93_256calls@0.93")}
HEADLINE_IMAGE = ("dense", "ddim:10", "every_n:5:timestep", "taylorseer:5:2", "file:digits_steps_0.8+taylor2",
                  "pruner:digits_tts_steps_0.8@0.8+taylor2", "taylorseer:3:2+ddim:20",
                  "file:digits_steps_ddim20_0.5+ddim:20+taylor2")


def headline_robot(folder: Path) -> str:
    """README: success over the test seeds, paired difference to dense, and the speed-up of a policy call
    measured against dense in one process at batch 1 and 28, where it was measured (from the frontier's
    latencies when they exist, else eval/latency.py's), and each sparse row against the best fewer-step
    sampler as fast."""
    runs = complete_runs(folder)
    speed: dict[tuple[str, str], dict[int, float]] = {}
    for path in sorted(folder.glob("latency_*.json")):
        r = json.loads(path.read_text())
        if r.get("parallel", "auto") == "auto" and r.get("reference", "dense") == "dense":
            speed[(r["task"], r["method"])] = {row["batch"]: row["speedup"] for row in r["rows"]}
    rows = ["| task | method | success (test episodes) | vs dense, paired (95% CI) | speed-up batch 1 / 28 "
            "| MACs dense DDPM-100 / method | minus the best fewer-step sampler as fast, batch 1 (paired 95% CI) |",
            "|---|---|---|---|---|---|---|"]
    for task, methods in HEADLINE_ROBOT.items():
        points = {p.method: p for p in frontier.frontier_points(folder, task, 1)}
        for batch in (1, 28):  # the frontier's one-process latencies take precedence over latency_*.json
            for p in frontier.frontier_points(folder, task, batch):
                if p.method != "dense":
                    speed.setdefault((task, p.method), {})[batch] = p.speedup
        rivals = []  # the fewer-step samplers the sparse rows are held against, shown after DDIM-7
        for method in methods:
            vs = frontier.beats_fewer_steps(points[method], list(points.values())) if method in points else None
            if vs is not None and vs[0].method not in methods + tuple(rivals):
                rivals.append(vs[0].method)
        at = methods.index("ddim:7") + 1 if "ddim:7" in methods else len(methods)
        for method in methods[:at] + tuple(rivals) + methods[at:]:
            rs = runs.get((task, method))
            if not rs:
                continue
            success, n = pooled(rs)
            paired = "-" if method == "dense" else paired_success_difference(rs, runs.get((task, "dense"), [])).split(" on ")[0]
            sp = speed.get((task, method), {})
            sp_text = " / ".join(f"{sp[b]:.2f}x" if b in sp else "-" for b in (1, 28)) if sp else "-"
            lc = rs[0].get("tts", {}).get("last_call", {})
            realised = lc.get("macs_realised_with_pruner", lc.get("macs_realised"))
            ref = runs[(task, "dense")][0]["tts"]["last_call"]["macs_dense"] if (task, "dense") in runs else None
            macs = f"{ref / realised:.1f}x" if realised and ref else "-"
            versus = _versus_fewer_steps(points[method], list(points.values()), 3) if method in points else "-"
            rows.append(f"| {task} | `{method}` | {success:.2f} ({n}) | {paired} | {sp_text} | {macs} | {versus} |")
    return "\n".join(rows) + "\n"


def headline_image(folder: Path) -> str:
    """README: FID and wall-clock speed-up of the main image rows, with DDIM-10 (the compute of 80% reuse)
    and, for each sparse row, the best fewer-step sampler (DDIM-k, DPM-Solver++-k) at least as fast and
    the FID difference to it (the frontier's conservative interval, batch 1). Speed-ups come from the
    frontier's one-process latencies where they exist, else from latency.json (the full tables:
    docs/results/image.md). MACs are against the dense 50-step run, also for a run on fewer steps."""
    speed: dict[str, dict[int, float]] = {}
    frontier_lat = folder / "frontier_latency.json"
    for path in (folder / "latency.json", frontier_lat):  # frontier_latency.json takes precedence over latency.json
        for row in json.loads(path.read_text())["rows"] if path.exists() else []:
            for name, m in row["methods"].items():
                speed.setdefault(name, {})[row["batch"]] = m["speedup"]
    batches = sorted({b for sp in speed.values() for b in sp})
    points = {p.method: p for p in frontier.image_frontier_points(folder, frontier_lat, 1)}
    by = {r["method"]: r for r in image_runs(folder)}
    rivals = []  # the fewer-step samplers the sparse rows are held against, shown after DDIM-10
    for name in HEADLINE_IMAGE:
        vs = frontier.beats_fewer_steps(points[name], list(points.values())) if name in points else None
        if vs is not None and vs[0].method not in HEADLINE_IMAGE + tuple(rivals):
            rivals.append(vs[0].method)
    at = HEADLINE_IMAGE.index("ddim:10") + 1
    versus_head = " | minus the best fewer-step sampler as fast, batch 1 (95% CI)" if points else ""
    rows = ["| method | FID | MACs speed-up | " + " | ".join(f"wall-clock speed-up, batch {b}" for b in batches)
            + versus_head + " |", "|---|---|---|" + "---|" * (len(batches) + bool(points))]
    for name in HEADLINE_IMAGE[:at] + tuple(rivals) + HEADLINE_IMAGE[at:]:
        r = by.get(name)
        if r is None:
            continue
        sp = speed.get(name, {})
        speeds = " | ".join("1.00x" if name == "dense" else f"{sp[b]:.2f}x" if b in sp else "-" for b in batches)
        versus = (" | " + (_versus_fewer_steps(points[name], list(points.values()), 2) if name in points else "-")
                  if points else "")
        rows.append(f"| `{name}` | {r.get('fid', float('nan')):.2f} | {_macs_speedup(r, by.get('dense')):.2f}x | "
                    f"{speeds}{versus} |")
    return "\n".join(rows) + "\n"


def fill(path: Path, tables: dict[str, str]) -> None:
    """Replace every marked block of ``path`` whose name is in ``tables``; a page without a block that
    ``tables`` names is an error (a table would silently go missing)."""
    body = path.read_text()
    for name, table in tables.items():
        begin, end = f"<!-- {name}-table:begin (eval/tables.py) -->", f"<!-- {name}-table:end -->"
        if begin not in body or end not in body:
            raise SystemExit(f"{path} has no block {begin} ... {end}")
        head, rest = body.split(begin, 1)
        body = head + begin + "\n" + table + end + rest.split(end, 1)[1]
    write_atomic(path, body)


def main() -> None:
    robot, image = REPO / "results" / "robot", REPO / "results" / "image"
    docs = REPO / "docs" / "results"
    fill(docs / "robot.md", {"robot": summary_table(robot), "latency": latency_table(robot),
                             "reuse-cost": reuse_cost_table(robot), "frontier": frontier_table(robot),
                             "gpu-frontier": frontier_table(robot, robot / "gpu"),
                             "sampler-families": sampler_families_table(robot),
                             "agreement": agreement_table(robot), "headroom": headroom_table(robot),
                             "rollout-age": rollout_age_table(robot),
                             "runs": robot_table(robot)})
    fill(docs / "testbed.md", {"steps": steps_table(robot), "table7": table7(robot),
                                "table7-vs-steps": table7_vs_steps(robot), "operators": operators_table(REPO / "results" / "experts"),
                                "push-operators": push_operators_table(REPO / "results" / "experts"),
                                "coverage": coverage_table(robot), "sample-spread": sample_spread_table(robot),
                                "pruner-training": pruner_training_table(REPO / "checkpoints" / "pruners")})
    fill(docs / "visuomotor.md", {"visuomotor": visuomotor_table(robot),
                                  "visuomotor-gpu": visuomotor_table(robot, robot / "gpu")})
    readme = {"headline-robot": headline_robot(robot)}
    if any(image.glob("digits_*.json")):
        sample_grids(image)
        fill(docs / "image.md", {"image": image_table(image), "image-frontier": image_frontier_table(image)})
        readme["headline-image"] = headline_image(image)
    fill(REPO / "README.md", readme)
    print(f"filled {docs / 'robot.md'}, {docs / 'image.md'} and README.md")


if __name__ == "__main__":
    main()
