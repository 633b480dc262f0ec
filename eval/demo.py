"""Demo (the README's main job until the robot pipeline lands): accelerate a Diffusion-Policy-sized
transformer (DDPM-100, static 93% plan) and a DiT-S/2-sized model (DDIM-50, CFG, static 80% plan),
print the wall-clock speed-up against dense in the same process, the MACs ratio and the output error.

Weights are random, so the output error only shows that reuse is approximate, not what it costs in
task quality (that is what eval/robot.py measures)."""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench import bench_dit, bench_dp  # noqa: E402


def main() -> None:
    torch.manual_seed(0)
    print("tts demo: static sparse plans, speed measured against dense in this process\n")
    r = bench_dp(batch=1, reps=3, sparsity=0.93)
    m = r["latency_s_median"]
    print(f"Diffusion Policy transformer, batch 1, {r['plan']}: realised sparsity {r['realised_sparsity']:.1%}")
    print(f"  dense (DP's stock loop) {m['dense_stock'] * 1e3:7.1f} ms | dense (fast loop) {m['dense_fast'] * 1e3:7.1f} ms"
          f" | tts {m['tts'] * 1e3:6.1f} ms")
    print(f"  speed-up {r['speedup_vs_dense_fast_loop']:.2f}x vs the same loop dense, "
          f"{r['speedup_vs_dense_stock_loop']:.2f}x vs the stock loop; "
          f"{r['macs_ratio_dense_fast_over_tts']:.2f}x fewer MACs; output rel. error {r['output_rel_error_vs_dense']:.3f}\n")
    r = bench_dit("official", reps=1, sparsity=0.8)
    m = r["latency_s_median"]
    print(f"{r['model']}, {r['plan']}: realised sparsity {r['realised_sparsity']:.1%}")
    print(f"  dense {m['dense']:.2f} s | tts {m['tts']:.2f} s | speed-up {r['speedup']:.2f}x; "
          f"{r['macs_ratio']:.2f}x fewer MACs; output rel. error {r['output_rel_error_vs_dense']:.3f}")


if __name__ == "__main__":
    main()
