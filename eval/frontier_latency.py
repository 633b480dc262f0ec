"""Policy-call latency of many methods against one dense reference, in one process, interleaved.

    python eval/frontier_latency.py --task lift --checkpoint checkpoints/lift_dpt \
        --trajectories data/trajectories/lift.pt --batch 1 28 \
        --methods ddim:2 ddim:7 dpm:3 file:results/schedules/lift_steps_0.93.json \
                  uniform:0.65:timestep+ddim:20

Every method gets its own copy of the policy with the method installed; dense is the untouched
policy. Per trial and batch size, every policy is timed on the same observation windows (reset, an
untimed frame 0, then ``--frames`` timed calls) in an order rotated per trial, so slow drift of the
machine hits all methods alike. Reported per method and batch: median latency and its ratio to the
dense median of the same trials (``speedup``), computed steps per call. The frontier table and plots
(eval/tables.py, eval/figures.py) join these ratios with the success rates of eval/robot.py.
Written atomically to ``results/robot/frontier_latency_<task>[-<policy>].json``; ``--resume``
keeps the methods and batches already in the file. ``--device cuda`` times on a GPU (each call
synchronised); its rows go to ``results/robot/gpu/`` by default, apart from the CPU frontier.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (REPO, add_all_episodes_option, add_device_option, parse_args, policy_slug, provenance,  # noqa: E402
                    torch_device, write_json)
from common.methods import ROBOT_KINDS, VOCABULARY, install_policy, parse_method  # noqa: E402
from common.policy_timing import batch_frames, computed_steps, time_calls  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.trajectories import load_trajectories  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--trajectories", type=Path, required=True,
                    help="observation windows (eval/collect_trajectories.py) of this task")
    ap.add_argument("--methods", nargs="+", required=True, help=f"each one of: {VOCABULARY}")
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 28])
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--frames", type=int, default=4, help="timed calls per trial (after the dense frame 0)")
    ap.add_argument("--first-episode", type=int, default=96, help="episodes used (default: past pruner training)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true", help="keep the (method, batch) rows already in --out")
    add_all_episodes_option(ap)
    add_device_option(ap)
    args = parse_args(ap, argv)
    device = torch_device(args.device)
    try:
        methods = [parse_method(m, kinds=ROBOT_KINDS) for m in args.methods]
    except ValueError as e:
        ap.error(str(e))
    labels = [m.label for m in methods]
    if len(set(labels)) != len(labels):
        ap.error(f"a method is listed twice: {labels}")
    folder = REPO / "results" / "robot" / ("gpu" if device.type == "cuda" else "")
    out = args.out or folder / f"frontier_latency_{policy_slug(args.task, args.checkpoint)}.json"
    rows: dict[str, dict] = {}
    if args.resume and out.exists():
        rows = {f"{r['method']}@{r['batch']}": r for r in json.loads(out.read_text())["rows"]}
    episodes, _ = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    pool = episodes[args.first_episode:] or episodes
    dense = load_policy(args.checkpoint).to(device)
    policies = {}
    for m in methods:
        pol = load_policy(args.checkpoint).to(device)
        policies[m.label] = (pol, install_policy(pol, m, parallel=False))
    for B in args.batch:
        todo = [lab for lab in labels if f"{lab}@{B}" not in rows]
        if not todo:
            continue
        eps = [pool[i % len(pool)] for i in range(B)]
        frames = batch_frames(dense, eps, args.frames)
        time_calls(dense, frames[:2], 0)
        for lab in todo:  # warm-up (allocator, MAC profile of the shape)
            pol, acc = policies[lab]
            time_calls(pol, frames, 0)
            acc.calls.clear()
        times: dict[str, list[float]] = {lab: [] for lab in ["dense"] + todo}
        order = ["dense"] + todo
        for trial in tqdm(range(args.trials), desc=f"{args.task} batch {B}: {len(todo)} methods"):
            shift = trial % len(order)
            for lab in order[shift:] + order[:shift]:
                pol = dense if lab == "dense" else policies[lab][0]
                times[lab].extend(time_calls(pol, frames, 1000 * trial))
        t_dense = float(np.median(times["dense"]))
        for lab in todo:
            acc = policies[lab][1]
            med = float(np.median(times[lab]))
            s = acc.summary()
            rows[f"{lab}@{B}"] = {
                "method": lab, "batch": B, "latency_ms": med * 1e3,
                "p90_ms": float(np.percentile(times[lab], 90)) * 1e3, "calls": len(times[lab]),
                "dense_ms": t_dense * 1e3, "speedup": t_dense / med, "computed_steps": computed_steps(s),
                "sampler": f"{policies[lab][0].cfg.scheduler}-{policies[lab][0].cfg.num_inference_steps}",
                "timing_median_ms": {k: v * 1e3 for k, v in s.timing().items()},
            }
            acc.calls.clear()
        res = {
            "provenance": provenance(seeds={"noise": "1000 * trial + frame"}),
            "task": args.task, "checkpoint": str(args.checkpoint), "policy": policy_slug(args.task, args.checkpoint),
            "trajectories": str(args.trajectories), "episodes_from": args.first_episode,
            "torch_threads": torch.get_num_threads(), "device": str(device),
            "protocol": "per batch size: every method and dense timed on the same windows, order rotated per "
                        "trial (reset, untimed frame 0, timed frames 1..frames); speedup = dense median / "
                        "method median of the same trials; pruners run before step 0 (no overlap thread)",
            "rows": sorted(rows.values(), key=lambda r: (r["batch"], r["method"])),
        }
        write_json(out, res)
        for lab in todo:
            r = rows[f"{lab}@{B}"]
            print(f"batch {B}: {lab}: {r['latency_ms']:.1f} ms, {r['speedup']:.2f}x dense ({r['computed_steps']} computed steps)")
    print(f"wrote {out}")
    return json.loads(out.read_text())


if __name__ == "__main__":
    main()
