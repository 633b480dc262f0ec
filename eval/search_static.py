"""BAC-style static schedule for a Diffusion Policy, searched offline from activation similarity.

    python eval/search_static.py --checkpoint checkpoints/lift_dpt --trajectories data/trajectories/lift.pt \
        --sparsity 0.93 --out results/schedules/lift_bac_0.93.json
    python eval/search_static.py --dit checkpoints/digits_dit --sparsity 0.8 --steps 50 --cfg 1.5 \
        --out results/schedules/digits_bac_0.8.json         # a DiT: calibration samples (seed 1, not the eval's 0)
    python eval/search_static.py --dit checkpoints/digits_dit --sparsity 0.8 --objective output --forecast 2 \
        --out results/schedules/digits_steps_0.8.json       # whole steps placed by output error

Runs dense calls on ``--calls`` recorded observation windows of the *training* trajectories (the
first ``--episodes``; never the test seeds), measures per branch how much its output changes between
denoising steps (:func:`tts.static_search.reuse_errors`) and picks per branch the compute steps that
hide the least change (:func:`tts.static_search.search_schedule`). Writes the decision grid (one
``C``/``T`` string per step), usable as ``eval/robot.py --method file:PATH``.

``--objective output`` searches instead one set of compute steps shared by every branch
(:func:`tts.static_search.search_compute_steps`): the loss is the L1 between the final output
(DiT sample / the policy's ``action_pred``) under the candidate schedule and the dense output from
the same noise, on the calibration samples, with ``--forecast`` as it will be used at test time.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import add_all_episodes_option, parse_args, provenance, write_json  # noqa: E402
from common.methods import ROBOT_KINDS, parse_method  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
import tts  # noqa: E402
from tts.static_search import reuse_errors, search_compute_steps, search_schedule, steps_grid  # noqa: E402
from tts.trajectories import Windows, load_trajectories  # noqa: E402


def policy_calibration(args):
    """Dense calls of the policy on recorded observation windows of the training trajectories."""
    episodes, _ = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    if not episodes:
        raise SystemExit(f"{args.trajectories} holds no successful episode; --all-episodes calibrates on the "
                         "states of every recorded episode (the target is the dense policy's own output either way)")
    policy = load_policy(args.checkpoint)
    windows = Windows(policy, episodes[:args.episodes])
    rng = np.random.default_rng(args.seed)
    pick = rng.choice(len(windows), size=min(args.calls, len(windows)), replace=False)
    if args.sampler:  # search over the steps of a shorter base sampler (ddim:K[:SPACING], dpm:K)
        base = parse_method(args.sampler, kinds=ROBOT_KINDS).sampler
        if base is None:
            raise SystemExit(f"--sampler takes ddim:K[:SPACING] or dpm:K, got {args.sampler!r}")
        policy.set_sampler(base.scheduler, base.steps, base.spacing)

    def sample():
        return torch.cat([policy.predict_action(windows.obs(pick[s:s + args.batch]),
                                                generator=torch.Generator().manual_seed(args.seed + s))["action_pred"]
                          for s in range(0, len(pick), args.batch)])

    return policy, sample, policy.cfg.num_inference_steps, 3 * policy.model.config.n_layer, len(pick)


def dit_calibration(args):
    """``--calls`` dense DDIM samples of the DiT (classes round-robin, noise seed ``--seed + 1``, so
    never the evaluation's samples, which use seed 0)."""
    from tts.adapters.dit import load_dit, sample_dit

    model = load_dit(args.dit)
    n_cls = model.y_embedder.num_classes

    def sample():
        g = torch.Generator().manual_seed(args.seed + 1)
        return torch.cat([sample_dit(model, torch.arange(s, min(s + args.batch, args.calls)) % n_cls,
                                     steps=args.steps, cfg_scale=args.cfg, generator=g)
                          for s in range(0, args.calls, args.batch)])

    return model, sample, args.steps, 2 * model.config.depth, args.calls


def output_search(model, sample, steps: int, branches: int, rho: float, args):
    """Compute steps shared by all branches, placed to minimise L1(sparse output, dense output)."""
    with torch.no_grad():
        target = sample()
    computes = max(1, round((1.0 - rho) * steps))

    def loss(compute_steps):
        plan = tts.plans.from_tensor(steps_grid(compute_steps, steps, branches))
        with torch.no_grad(), tts.accelerate(model, ("timestep",), plan=plan, forecast=args.forecast):
            return float((sample() - target).abs().mean())

    shifts = [int(x) for x in args.shifts.split(",")]
    best, history = search_compute_steps(loss, steps, computes, max_sweeps=args.sweeps, shifts=shifts,
                                         log=lambda msg: print(msg, flush=True))
    return steps_grid(best, steps, branches), {"compute_steps": best, "search_history": history,
                                               "forecast": args.forecast}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=None, help="a Diffusion Policy (with --trajectories)")
    ap.add_argument("--trajectories", type=Path, default=None)
    ap.add_argument("--dit", type=Path, default=None, help="a class-conditional DiT instead (tts.adapters.dit.load_dit)")
    ap.add_argument("--steps", type=int, default=50, help="--dit: DDIM steps")
    ap.add_argument("--cfg", type=float, default=1.5, help="--dit: guidance scale")
    ap.add_argument("--sampler", default=None,
                    help="policy: the base sampler the schedule is for (ddim:K[:SPACING] or dpm:K; default the "
                         "policy's DDPM-100); evaluate it as file:SCHEDULE+ddim:K")
    ap.add_argument("--sparsity", type=float, nargs="+", default=[0.93])
    ap.add_argument("--episodes", type=int, default=32, help="calibration episodes (from the start of the file)")
    add_all_episodes_option(ap)
    ap.add_argument("--calls", type=int, default=64, help="calibration policy calls (spread over the episodes)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--objective", choices=["similarity", "output"], default="similarity",
                    help="similarity: BAC-style per-branch DP on activation change; output: one set of compute "
                         "steps for all branches, local search on the final output's L1 to dense")
    ap.add_argument("--forecast", type=int, default=0, help="--objective output: Taylor forecast order used in the search")
    ap.add_argument("--sweeps", type=int, default=6, help="--objective output: at most this many local-search sweeps")
    ap.add_argument("--shifts", default="1,2,3", help="--objective output: how far one move shifts a compute step")
    ap.add_argument("--out", type=Path, required=True, help="output JSON; with several sparsities, one file each "
                    "named <out stem>_<sparsity>.json")
    args = parse_args(ap, argv)
    if (args.dit is None) == (args.checkpoint is None):
        raise SystemExit("give either --checkpoint (with --trajectories) or --dit")
    if args.forecast and args.objective != "output":
        raise SystemExit("--forecast applies to --objective output")
    if args.dit is not None:
        model, sample, steps, branches, n_calls = dit_calibration(args)
    else:
        if args.trajectories is None:
            raise SystemExit("--checkpoint needs --trajectories (calibration observations)")
        model, sample, steps, branches, n_calls = policy_calibration(args)
    errors = reuse_errors(model, sample) if args.objective == "similarity" else None
    written = {}
    for rho in args.sparsity:
        tts.plans.check_sparsity(rho)
        if errors is not None:
            grid, extra = search_schedule(errors, rho), {}
        else:
            grid, extra = output_search(model, sample, steps, branches, rho, args)
        out = args.out if len(args.sparsity) == 1 else args.out.with_name(f"{args.out.stem}_{rho:g}.json")
        doc = {
            "provenance": provenance(seeds={"calibration": args.seed}),
            "method": ("BAC-style per-branch DP on activation similarity (timestep reuse)" if errors is not None
                       else "compute steps shared by all branches, local search on output L1 to dense"),
            "model": str(args.dit or args.checkpoint), "trajectories": str(args.trajectories),
            "calibration_episodes": args.episodes, "calibration_calls": args.calls,
            "calibration_calls_used": n_calls,  # --calls, capped by the windows of --episodes
            "calibration_on": "every recorded episode" if args.all_episodes else "successful episodes",
            "sparsity": rho, "realised_sparsity": float((grid != 0).float().mean()),
            "sampler": args.sampler or "the policy's own",
            "directions": ["timestep"],
            "grid": ["".join("CFTR"[c] for c in row.tolist()) for row in grid], **extra,
        }
        write_json(out, doc)
        written[rho] = str(out)
        print(f"sparsity {rho}: computes per branch {int((grid == 0).sum(0)[0])}/{grid.shape[0]}; wrote {out}")
    return written


if __name__ == "__main__":
    main()
