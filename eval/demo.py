"""Main job on the bundled default: the bundled Lift Diffusion Policy in robosuite, dense vs a static
93%-sparse schedule (searched offline by eval/search_static.py), a few test episodes each; prints
success and the policy-call speed-up measured in this process.

    python eval/demo.py [--episodes 5] [--plan file:results/schedules/lift_steps_0.93.json] [--engine]

``--engine`` instead runs the engine benchmark on a DP-sized transformer and a DiT-S/2 (random
weights: speed and MACs only).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402

DEFAULT_CKPT = REPO / "checkpoints" / "lift_dpt"


def robot_demo(checkpoint: Path, episodes: int, plan_spec: str, seed: int) -> None:
    import tts
    from robot import parse_plan, run_wave
    from tts.adapters.dp_policy import load_policy
    from tts.adapters.robosuite_tasks import make_env

    policy = load_policy(checkpoint)
    envs = [make_env("lift") for _ in range(episodes)]
    seeds = list(range(seed, seed + episodes))
    print(f"tts demo: {checkpoint.name} on robosuite Lift, {episodes} test episodes (seeds {seeds[0]}..{seeds[-1]}),"
          f" batch {episodes} (one env per episode)\n")
    results = {}
    name = Path(plan_spec[5:]).stem if plan_spec.startswith("file:") else plan_spec
    for label, spec in (("dense", "dense"), (f"tts {name}", plan_spec)):
        directions, plan = parse_plan(spec)
        with tts.accelerate(policy, directions, plan=plan) as acc:
            outcomes, lat = run_wave(policy, envs, seeds, "lift", torch.Generator().manual_seed(seed))
            s = acc.summary()
        dense_macs, realised = s.macs(s.calls[-1])
        results[label] = np.median(lat)
        print(f"{label:>28}: success {sum(o['success'] for o in outcomes)}/{episodes}, "
              f"policy call {np.median(lat) * 1e3:6.1f} ms (median of {len(lat)}), "
              f"sparsity {s.sparsity():.1%}, decoder MACs {dense_macs / max(realised, 1):.1f}x fewer")
    dense, sparse = results.values()
    print(f"\nspeed-up of a policy call: {dense / sparse:.2f}x (scripted-expert demonstrations, not human data)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=DEFAULT_CKPT)
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--plan", default="file:results/schedules/lift_steps_0.93.json",
                    help="a static plan: file:<searched schedule JSON> (relative to the repo), uniform:<s>:<dir>, ...")
    ap.add_argument("--seed", type=int, default=100000)
    ap.add_argument("--engine", action="store_true", help="engine benchmark on random-weight models instead")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    if args.engine:
        from bench import bench_dit, bench_dp

        r = bench_dp(batch=1, reps=3, sparsity=0.93)
        print(f"DP-T batch 1, {r['plan']}: {r['speedup_vs_dense_fast_loop']:.2f}x vs dense (same loop), "
              f"{r['macs_ratio_dense_fast_over_tts']:.2f}x fewer MACs, output rel. error {r['output_rel_error_vs_dense']:.3f}")
        r = bench_dit("official", reps=1, sparsity=0.8)
        print(f"DiT-S/2, {r['plan']}: {r['speedup']:.2f}x, {r['macs_ratio']:.2f}x fewer MACs, "
              f"output rel. error {r['output_rel_error_vs_dense']:.3f}")
        return
    if not checkpoint_pair(args.checkpoint)[1].exists():
        raise SystemExit(f"{args.checkpoint}.json not found: train it with eval/train_policy.py (see README)")
    plan = args.plan
    if plan.startswith("file:") and not Path(plan[5:]).is_absolute():
        plan = f"file:{REPO / plan[5:]}"
    robot_demo(args.checkpoint, args.episodes, plan, args.seed)


if __name__ == "__main__":
    main()
