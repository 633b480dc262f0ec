"""Wall-clock of one DiT sampling call, every method against dense, in one process.

    python eval/image_latency.py --model checkpoints/digits_dit --pruner checkpoints/pruners/digits_tts_0.8 \
        --plan results/schedules/digits_bac_0.8.json --sparsity 0.8 --batch 1 16 --out results/image/latency.json

Per batch size B (images; CFG doubles the rows) and trial, every method samples the same B labels
from the same noise (DDIM ``--steps``, guidance ``--cfg``) once, in a rotating order; dense is the
untouched model. Speed-up = dense median / method median over ``--trials``. The methods and their
settings are eval/imagenet.py's (``build_accelerator``), so the numbers belong to the FID table's rows.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import parse_args, provenance, write_json  # noqa: E402
from imagenet import build_accelerator, describe, last_call_counts, sample_noise, sampler_of  # noqa: E402

from tts.adapters.dit import load_dit, sample_dit  # noqa: E402

# (label, eval/imagenet.py arguments): the rows of scripts/image_table.sh
METHODS = {
    "fora_n5": dict(method="fora", fora_n=5),
    "taylorseer_n5_o2": dict(method="taylorseer", fora_n=5, taylor_order=2),
    "toca_n6": dict(method="toca", fora_n=6, use_sparsity=True),
    "duca_n6": dict(method="duca", fora_n=6, use_sparsity=True),
    "static_bac": dict(method="static"),
    "tts": dict(method="tts", use_sparsity=True),
    "static_bac_taylor2": dict(method="static", forecast=2),
    "tts_taylor2": dict(method="tts", use_sparsity=True, forecast=2, pruner="taylor"),
    "steps_o2": dict(method="static", forecast=2, plan="steps"),
    "tts_steps_o2": dict(method="tts", use_sparsity=True, forecast=2, pruner="steps"),
    "diffusers_fbc": dict(method="diffusers_fbc", use_sparsity=True),
    "diffusers_taylorseer_n5_o2": dict(method="diffusers_taylorseer", fora_n=5, taylor_order=2),
}


def method_args(name: str, args: argparse.Namespace) -> argparse.Namespace:
    spec = dict(METHODS[name])
    use_sparsity = spec.pop("use_sparsity", False)
    pruner = {"taylor": args.pruner_taylor, "steps": args.pruner_steps, None: args.pruner}[spec.pop("pruner", None)]
    plan = args.plan_steps if spec.pop("plan", None) == "steps" else args.plan
    ns = argparse.Namespace(method=None, fora_n=5, taylor_order=1, fresh_ratio=None, plan=plan, forecast=0,
                            pruner=str(pruner) if pruner else None, fbc_threshold=None, calib_seed=1,
                            steps=args.steps, cfg=args.cfg, sparsity=args.sparsity if use_sparsity else None)
    for k, v in spec.items():
        setattr(ns, k, v)
    return ns


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--pruner", type=Path, default=None, help="for the tts row")
    ap.add_argument("--pruner-taylor", type=Path, default=None, help="pruner trained with --forecast 2 (tts_taylor2 row)")
    ap.add_argument("--pruner-steps", type=Path, default=None,
                    help="pruner started from the searched compute steps, with --forecast 2 (tts_steps_o2 row)")
    ap.add_argument("--plan", default=None, help="searched schedule, for the static_bac rows")
    ap.add_argument("--plan-steps", default=None, help="searched compute steps (search_static.py --objective "
                    "output --forecast 2), for the steps_o2 row")
    ap.add_argument("--sparsity", type=float, default=0.8)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--cfg", type=float, default=1.5)
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--trials", type=int, default=7)
    ap.add_argument("--out", type=Path, required=True)
    args = parse_args(ap, argv)
    names = [m for m in args.methods.split(",") if m]
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    missing = {"tts": args.pruner, "tts_taylor2": args.pruner_taylor, "static_bac": args.plan,
               "static_bac_taylor2": args.plan, "steps_o2": args.plan_steps, "tts_steps_o2": args.pruner_steps}
    names = [m for m in names if m not in missing or missing[m] is not None]
    dense = load_dit(args.model).eval()
    models = {"dense": (dense, None)}
    for name in names:
        m = load_dit(args.model).eval()
        acc = build_accelerator(m, method_args(name, args))
        models[name] = (sampler_of(m, acc), acc)
    size, C, n_cls = dense.config.input_size, dense.in_channels, dense.config.num_classes
    rows = []
    for B in args.batch:
        labels = torch.arange(B) % n_cls
        noise = sample_noise(12345, range(B), (C, size, size))
        times: dict[str, list[float]] = {k: [] for k in models}
        order = list(models)
        for trial in tqdm(range(args.trials + 1), desc=f"latency batch {B}"):
            for name in order[trial % len(order):] + order[:trial % len(order)]:
                model, acc = models[name]
                t0 = time.perf_counter()
                sample_dit(model, labels, steps=args.steps, cfg_scale=args.cfg, noise=noise)
                if trial:  # trial 0 warms up (allocator, MAC profiling of the first shape)
                    times[name].append(time.perf_counter() - t0)
        md = float(np.median(times["dense"]))
        row = {"batch": B, "dense_ms": md * 1e3, "methods": {}}
        for name in names:
            model, acc = models[name]
            c = last_call_counts(acc)
            mf = float(np.median(times[name]))
            row["methods"][name] = {
                "plan": describe(acc), "ms": mf * 1e3, "speedup": md / mf,
                "macs_ratio": c["macs_dense"] / max(c["macs_realised"] + c["macs_pruner"], 1.0),
                "sparsity_decisions": c["reused"] / max(c["decisions"], 1),
            }
            print(f"batch {B}: {name:18s} {mf * 1e3:8.1f} ms vs dense {md * 1e3:8.1f} ms -> {md / mf:5.2f}x "
                  f"(MACs {row['methods'][name]['macs_ratio']:.2f}x)")
        rows.append(row)
    res = {"provenance": provenance(seeds={"noise": "sample_noise(12345, range(B))"}), "model": args.model,
           "steps": args.steps, "cfg_scale": args.cfg, "sparsity": args.sparsity, "trials": args.trials,
           "torch_threads": torch.get_num_threads(),
           "protocol": "same labels and noise for every method; rotating order per trial; trial 0 untimed; medians",
           "rows": rows}
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
