"""Wall-clock of one DiT sampling call, every method against dense, in one process.

    python eval/image_latency.py --model checkpoints/digits_dit --batch 1 16 --out results/image/latency.json \
        --methods every_n:5:timestep taylorseer:5:2 pruner:checkpoints/pruners/digits_tts_0.8@0.8 ...

``--methods``: specs of the vocabulary of eval/imagenet.py (eval/common/methods.py), fewer-step
samplers (``ddim:K``, ``dpm:K``) and engine methods on their own base (``SPEC+ddim:20``) included. Per
batch size B (images; CFG doubles the rows) and trial, every method samples the same B labels from
the same noise (guidance ``--cfg``) once, in a rotating order; dense is the untouched model with DDIM
``--steps``, and every method runs its own sampler (``--steps`` DDIM unless the spec names one).
Speed-up = dense median / method median over ``--trials``. Rows are keyed by the method's label, as
the FID runs of eval/imagenet.py are, so the table joins them; each row records its sampler.
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
from common.methods import IMAGE_KINDS, VOCABULARY, parse_method  # noqa: E402
from image_suite.sampling import (build_accelerator, describe, last_call_counts, sample_noise,  # noqa: E402
                                  sampler_of, sampler_steps)

from tts.adapters.dit import load_dit, sample_dit  # noqa: E402

def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--methods", nargs="+", required=True, help=f"specs of: {VOCABULARY}")
    ap.add_argument("--calib-seed", type=int, default=1, help="diffusers:fbc@RHO: calibration noise seed")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--cfg", type=float, default=1.5)
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--trials", type=int, default=7)
    ap.add_argument("--out", type=Path, required=True)
    args = parse_args(ap, argv)
    try:
        methods = [parse_method(spec, kinds=IMAGE_KINDS - {"dense"}) for spec in args.methods]
    except ValueError as e:
        ap.error(str(e))
    names = [m.label for m in methods]
    dense = load_dit(args.model).eval()
    models = {"dense": (dense, None, args.steps, "ddim")}
    for method in methods:
        steps, scheduler = sampler_steps(method, args.steps, "ddim")
        m = load_dit(args.model).eval()
        acc = build_accelerator(m, method, steps=steps, cfg=args.cfg, calib_seed=args.calib_seed)
        models[method.label] = (sampler_of(m, acc), acc, steps, scheduler)
    size, C, n_cls = dense.config.input_size, dense.in_channels, dense.config.num_classes
    rows = []
    for B in args.batch:
        labels = torch.arange(B) % n_cls
        noise = sample_noise(12345, range(B), (C, size, size))
        times: dict[str, list[float]] = {k: [] for k in models}
        order = list(models)
        for trial in tqdm(range(args.trials + 1), desc=f"latency batch {B}"):
            for name in order[trial % len(order):] + order[:trial % len(order)]:
                model, acc, steps, scheduler = models[name]
                t0 = time.perf_counter()
                sample_dit(model, labels, steps=steps, cfg_scale=args.cfg, noise=noise, scheduler=scheduler)
                if trial:  # trial 0 warms up (allocator, MAC profiling of the first shape)
                    times[name].append(time.perf_counter() - t0)
        md = float(np.median(times["dense"]))
        row = {"batch": B, "dense_ms": md * 1e3, "methods": {}}
        for name in names:
            model, acc, steps, scheduler = models[name]
            mf = float(np.median(times[name]))
            entry = {"sampler": f"{scheduler}:{steps}", "ms": mf * 1e3, "speedup": md / mf}
            if acc is None:  # a fewer-step sampler: the untouched model, steps / dense steps of its MACs
                entry.update(plan="dense", macs_ratio=args.steps / steps, sparsity_decisions=0.0)
            else:  # MACs against the dense call on the method's own base sampler
                c = last_call_counts(acc)
                entry.update(plan=describe(acc), sparsity_decisions=c["reused"] / max(c["decisions"], 1),
                             macs_ratio=c["macs_dense"] / max(c["macs_realised"] + c["macs_pruner"], 1.0)
                             * args.steps / steps)
            row["methods"][name] = entry
            print(f"batch {B}: {name:28s} {mf * 1e3:8.1f} ms vs dense {md * 1e3:8.1f} ms -> {md / mf:5.2f}x "
                  f"(MACs {entry['macs_ratio']:.2f}x)")
        rows.append(row)
    res = {"provenance": provenance(seeds={"noise": "sample_noise(12345, range(B))"}), "model": args.model,
           "steps": args.steps, "cfg_scale": args.cfg, "trials": args.trials,
           "torch_threads": torch.get_num_threads(),
           "protocol": "same labels and noise for every method; rotating order per trial; trial 0 untimed; medians",
           "rows": rows}
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
