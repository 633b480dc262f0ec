"""Main job on the bundled default: the bundled Lift Diffusion Policy in robosuite, dense vs a static
93%-sparse schedule (searched offline by eval/search_static.py) vs DDIM with 7 steps (the same
compute), a few test episodes each; prints success and the policy-call speed-up measured in this
process.

    python eval/demo.py [--episodes 5] [--method file:results/schedules/lift_steps_0.93.json] [--engine]

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
from common.methods import ROBOT_KINDS, VOCABULARY, Method, install, parse_method  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402

DEFAULT_CKPT = REPO / "checkpoints" / "lift_dpt"


def robot_demo(checkpoint: Path, episodes: int, method: Method, seed: int) -> None:
    from robot_suite.rollout import run_wave
    from robot_suite.tasks import make_env
    from tts.adapters.dp_policy import load_policy

    policy = load_policy(checkpoint)
    envs = [make_env("lift") for _ in range(episodes)]
    seeds = list(range(seed, seed + episodes))
    print(f"tts demo: {checkpoint.name} on robosuite Lift, {episodes} test episodes (seeds {seeds[0]}..{seeds[-1]}),"
          f" batch {episodes} (one env per episode)\n")
    results = {}
    base = (policy.cfg.scheduler, policy.cfg.num_inference_steps)
    dense = parse_method("dense", kinds=ROBOT_KINDS)
    for label, m, sampler in (("dense", dense, base), (f"tts {method.label}", method, base),
                              ("fewer steps: ddim:7", dense, ("ddim", 7))):
        policy.set_sampler(*sampler)
        with install(policy, m) as acc:
            outcomes, lat = run_wave(policy, envs, seeds, "lift", torch.Generator().manual_seed(seed))
            s = acc.summary()
        macs = s.macs(s.calls[-1])[1]
        results[label] = (float(np.median(lat)), macs)
        print(f"{label:>28}: success {sum(o['success'] for o in outcomes)}/{episodes}, "
              f"policy call {np.median(lat) * 1e3:6.1f} ms (median of {len(lat)}), sparsity {s.sparsity():.1%}, "
              f"decoder MACs {results['dense'][1] / max(macs, 1):.1f}x fewer than dense")
    policy.set_sampler(*base)
    (t_dense, _), (t_tts, _), (t_ddim, _) = results.values()
    print(f"\nspeed-up of a policy call over dense: {t_dense / t_tts:.2f}x with tts, {t_dense / t_ddim:.2f}x with "
          "DDIM-7 (the same compute; on these easy scripted-expert policies fewer steps do as well)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=DEFAULT_CKPT)
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--method", default="file:results/schedules/lift_steps_0.93.json",
                    help=f"a static plan or pruner (paths relative to the repo): {VOCABULARY}")
    ap.add_argument("--seed", type=int, default=100000)
    ap.add_argument("--engine", action="store_true", help="engine benchmark on random-weight models instead")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads of the robot demo (default 1: a policy this small gains little from a "
                         "second thread, and waking it after every batch of env steps can cost more than a "
                         "short call, which distorts the speed-ups)")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    if args.engine:
        from common.engine_bench import bench_dit, bench_dp

        r = bench_dp(batch=1, reps=3, sparsity=0.93)
        print(f"DP-T batch 1, {r['plan']}: {r['speedup_vs_dense_fast_loop']:.2f}x vs dense (same loop), "
              f"{r['macs_ratio_dense_fast_over_tts']:.2f}x fewer MACs, output rel. error {r['output_rel_error_vs_dense']:.3f}")
        r = bench_dit("official", reps=1, sparsity=0.8)
        print(f"DiT-S/2, {r['plan']}: {r['speedup']:.2f}x, {r['macs_ratio']:.2f}x fewer MACs, "
              f"output rel. error {r['output_rel_error_vs_dense']:.3f}")
        return
    if not checkpoint_pair(args.checkpoint)[1].exists():
        raise SystemExit(f"{args.checkpoint}.json not found: train it with eval/train_policy.py (see README)")
    method = parse_method(args.method, kinds=ROBOT_KINDS)
    if method.kind == "ddim" or method.kind == "dense":
        raise SystemExit("--method: give a sparse plan or pruner to compare with dense")
    if method.path is not None and not method.path.is_absolute():
        method = parse_method(args.method.replace(str(method.path), str(REPO / method.path), 1), kinds=ROBOT_KINDS)
    torch.set_num_threads(args.threads)
    robot_demo(args.checkpoint, args.episodes, method, args.seed)


if __name__ == "__main__":
    main()
