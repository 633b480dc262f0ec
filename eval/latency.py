"""Policy-call latency of an accelerated policy against dense, measured in one process.

    python eval/latency.py --task lift --checkpoint checkpoints/lift_dpt \
        --method pruner:checkpoints/pruners/lift_tts_0.93@0.93 --trajectories data/trajectories/lift.pt --batch 1 28

``--method``: the vocabulary of eval/robot.py (eval/common/methods.py; ``ddim:K`` times the DDIM-K sampler,
dense). Protocol: real observation windows from recorded dense trajectories. Per
trial and batch size B, take B episodes; ``reset()``; frame 0 (the dense call that fills the rollout
cache, untimed); then time the calls on frames 1..``--frames``. Dense is the untouched policy (its own
fast loop: batched condition encoder, precomputed DDPM coefficients), timed in the same trials,
alternating order. Reported per batch size: median latency of a policy call, speed-up = dense median
/ accelerated median, calls/s (= 1 / latency) and actions/s per env (= n_action_steps / latency),
realised sparsity, MACs (dense, realised, pruner, realised + pruner) and the median timing breakdown
of the accelerated call (encoder, pruner, wait, decoder, reuse_steps, engine, scheduler_and_rest,
total) from ``summary()``.

``--reference`` replaces dense by another method as the baseline timed alongside, e.g. ``ddim:7``, or
``ddim:matched``: DDIM with as many steps as the accelerated call computes (per sample, rounded), the
cost of the reuse steps made visible (``ratio`` = accelerated / reference latency).

``--device cuda`` times on a GPU (each call synchronised; the pruner runs on a side CUDA stream beside
step 0 unless ``--parallel off``); its rows go to ``results/robot/gpu/`` by default, apart from the CPU
rows.
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
from common import methods  # noqa: E402
from common.methods import ROBOT_KINDS, VOCABULARY, parse_method  # noqa: E402
from common.policy_timing import batch_frames, computed_steps, time_calls, timed_image_encoder  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.trajectories import load_trajectories  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--trajectories", type=Path, required=True, help="observation windows (eval/collect_trajectories.py)")
    ap.add_argument("--method", required=True, help=f"one of: {VOCABULARY}")
    ap.add_argument("--parallel", choices=["auto", "on", "off"], default="auto",
                    help="pruner overlap with step 0 (worker thread on CPU; auto: only with idle cores)")
    ap.add_argument("--forecast", type=int, default=0, help="TaylorSeer-style forecast order for timestep reuse")
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 28])
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--frames", type=int, default=4, help="timed calls per trial (after the dense frame 0)")
    ap.add_argument("--first-episode", type=int, default=96, help="episodes used (default: past the pruner's training set)")
    ap.add_argument("--reference", default="dense",
                    help="the baseline timed alongside: dense (default), a method spec, or ddim:matched (DDIM with "
                         "the accelerated call's number of computed steps)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true", help="skip when the result file exists")
    add_all_episodes_option(ap)
    add_device_option(ap)
    args = parse_args(ap, argv)
    device = torch_device(args.device)
    method = parse_method(args.method, kinds=ROBOT_KINDS, forecast=args.forecast)
    matched = args.reference == "ddim:matched"
    reference = None if args.reference == "dense" or matched else parse_method(args.reference, kinds=ROBOT_KINDS)
    label = method.label
    suffix = "" if args.parallel == "auto" else f"_parallel-{args.parallel}"
    if args.reference != "dense":
        suffix += "_vs_" + ("ddim-matched" if matched else reference.slug)
    name = f"latency_{policy_slug(args.task, args.checkpoint)}_{method.slug}{suffix}.json"
    out_path = args.out or REPO / "results" / "robot" / ("gpu" if device.type == "cuda" else "") / name
    if args.resume and out_path.exists():
        print(f"[skip] {out_path} exists")
        return json.loads(out_path.read_text())
    episodes, _ = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    pool = episodes[args.first_episode:] or episodes
    dense = load_policy(args.checkpoint).to(device)
    fast = load_policy(args.checkpoint).to(device)
    acc = methods.install_policy(fast, method, parallel={"auto": "auto", "on": True, "off": False}[args.parallel])
    ref_acc = methods.install_policy(dense, reference) if reference is not None else None
    rows = []
    for B in args.batch:
        eps = [pool[i % len(pool)] for i in range(B)]
        frames = batch_frames(dense, eps, args.frames)
        time_calls(fast, frames, 0)  # warm-up (allocator, profiling of the first shape)
        if matched:
            steps = computed_steps(acc.summary())
            if ref_acc is not None:
                ref_acc.remove()
            ref_acc = methods.install_policy(dense.set_sampler("ddpm", dense.cfg.num_train_timesteps),
                                             parse_method(f"ddim:{steps}", kinds=ROBOT_KINDS))
        time_calls(dense, frames[:2], 0)
        acc.calls.clear()
        if ref_acc is not None:
            ref_acc.calls.clear()
        t_dense, t_fast = [], []
        with timed_image_encoder(dense) as t_encoder:
            for trial in tqdm(range(args.trials), desc=f"latency batch {B}"):
                order = (dense, fast) if trial % 2 == 0 else (fast, dense)
                for pol in order:
                    (t_dense if pol is dense else t_fast).extend(time_calls(pol, frames, 1000 * trial))
        s = acc.summary()
        sparse_calls = [c for c in s.calls if not c.dense]
        last = sparse_calls[-1]
        macs_dense, macs_real = s.macs(last)
        md, mf = float(np.median(t_dense)), float(np.median(t_fast))
        n_act = dense.cfg.n_action_steps
        ref_info = {}
        if ref_acc is not None:
            rs = ref_acc.summary()
            ref_info = {"reference": ref_acc.plan.describe() if not matched else f"ddim:{steps}",
                        "reference_sampler": f"{dense.cfg.scheduler}-{dense.cfg.num_inference_steps}",
                        "ratio": mf / md,
                        "reference_timing_median_ms": {k: v * 1e3 for k, v in rs.timing().items()},
                        "computed_steps_per_call": computed_steps(s)}
        rows.append({
            "batch": B, **ref_info,
            ("dense_ms" if ref_acc is None else "reference_ms"): {"median": md * 1e3, "p90": float(np.percentile(t_dense, 90)) * 1e3, "calls": len(t_dense)},
            "accelerated_ms": {"median": mf * 1e3, "p90": float(np.percentile(t_fast, 90)) * 1e3, "calls": len(t_fast)},
            "speedup": md / mf,
            "calls_per_s": {"dense": 1 / md, "accelerated": 1 / mf},
            "actions_per_s_per_env": {"dense": n_act / md, "accelerated": n_act / mf},
            "sparsity": s.sparsity(sparse_calls),
            "macs_per_call": {"dense": macs_dense, "realised": macs_real, "pruner": last.pruner_macs,
                              "realised_with_pruner": macs_real + last.pruner_macs},
            "timing_median_ms": {k: v * 1e3 for k, v in s.timing(sparse_calls).items()},
        })
        if t_encoder:  # an image policy: the encoder's share of each call
            enc_ms = float(np.median(t_encoder)) * 1e3
            rows[-1]["image_encoder_ms"] = {("dense" if ref_acc is None else "reference"): enc_ms,
                                            "accelerated": rows[-1]["timing_median_ms"].get("image_encoder", float("nan"))}
        r = rows[-1]
        ref_name = "dense" if ref_acc is None else f"{dense.cfg.scheduler}-{dense.cfg.num_inference_steps}"
        print(f"batch {B}: {ref_name} {md * 1e3:.1f} ms, {label} {mf * 1e3:.1f} ms -> {r['speedup']:.2f}x; "
              f"sparsity {r['sparsity']:.3f}; MACs {macs_dense / max(macs_real + last.pruner_macs, 1):.2f}x fewer "
              f"(pruner included); breakdown {', '.join(f'{k} {v:.1f}' for k, v in r['timing_median_ms'].items())}")
    res = {
        "provenance": provenance(seeds={"noise": "1000 * trial + frame"}),
        "task": args.task, "checkpoint": str(args.checkpoint), "method": label, "parallel": args.parallel,
        "reference": args.reference, "torch_threads": torch.get_num_threads(), "device": str(device),
        "trajectories": str(args.trajectories), "episodes_from": args.first_episode,
        "protocol": "per trial: reset, untimed dense frame 0, timed frames 1..frames; dense = untouched policy, "
                    "same trials, alternating order; medians",
        "hz_definitions": "calls_per_s = 1 / median call latency; actions_per_s_per_env = n_action_steps / median latency",
        "rows": rows,
    }
    write_json(out_path, res)
    print(f"wrote {out_path}")
    return res


if __name__ == "__main__":
    main()
