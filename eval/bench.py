"""Engine benchmark: wall-clock and MACs of static sparse plans against dense, in one process.

    python eval/bench.py [--quick] [--out results/bench_engine.json]

- Diffusion-Policy-sized transformer (8 decoder layers, width 256, 4 heads, horizon 10, DDPM-100):
  static 93%-sparse plan (7 full steps, timestep reuse) at batch 1 and batch 28, and at batch 28 a
  plan where every sample has its own random 93% decisions (gather/scatter path), against DP's stock
  loop (encoder + ``DDPMScheduler.step`` every step) and against the same fast loop run dense
  (encoder once per call, precomputed DDPM coefficients).
- DiT-S/2-sized models (diffusers ``DiTTransformer2DModel`` and the official timm layout), DDIM-50,
  classifier-free guidance batched as [cond; uncond]: static 80%-sparse plan.

Timings interleave the methods rep by rep (same process, same inputs, same noise). Weights are
random: this measures speed and MACs, not quality (output error is reported for orientation only).
MACs come from PyTorch's FlopCounterMode on one real call of each method (FLOPs / 2).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, provenance, write_atomic, write_json, parse_args  # noqa: E402
from common.engine_bench import bench_dit, bench_dp, to_markdown  # noqa: E402



def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer reps, batch 1 DP and diffusers DiT only")
    ap.add_argument("--out", type=Path, default=REPO / "results" / "bench_engine.json")
    args = parse_args(ap, argv)
    reps = 2 if args.quick else 5
    res = {"provenance": provenance(seeds={"torch": 0, "cond": 1, "noise": 2}), "diffusion_policy": [], "dit": []}
    for batch, per_sample in ([(1, False)] if args.quick else [(1, False), (28, False), (28, True)]):
        print(f"[bench] DP-T batch {batch}{' per-sample plan' if per_sample else ''} ...", flush=True)
        r = bench_dp(batch, reps if batch == 1 else max(2, reps - 2), 0.93, per_sample)
        res["diffusion_policy"].append(r)
        print(f"  tts {r['latency_s_median']['tts']:.4f}s vs dense fast {r['latency_s_median']['dense_fast']:.3f}s "
              f"({r['speedup_vs_dense_fast_loop']:.2f}x), vs stock {r['speedup_vs_dense_stock_loop']:.2f}x, "
              f"MACs {r['macs_ratio_dense_fast_over_tts']:.2f}x fewer", flush=True)
    for kind in (["diffusers"] if args.quick else ["diffusers", "official"]):
        print(f"[bench] DiT-S/2 ({kind}) ...", flush=True)
        r = bench_dit(kind, 1 if args.quick else 2, 0.8)
        res["dit"].append(r)
        print(f"  tts {r['latency_s_median']['tts']:.3f}s vs dense {r['latency_s_median']['dense']:.3f}s "
              f"({r['speedup']:.2f}x), MACs {r['macs_ratio']:.2f}x fewer", flush=True)
    write_json(args.out, res)
    write_atomic(args.out.with_suffix(".md"), to_markdown(res))
    print(f"[bench] wrote {args.out} and {args.out.with_suffix('.md')}")
    return res


if __name__ == "__main__":
    main()
