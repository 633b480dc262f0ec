"""Headroom for per-observation decisions around a searched whole-step schedule.

    python eval/oracle_headroom.py --task can --checkpoint checkpoints/can_dpt --trajectories data/trajectories/can.pt \
        --schedule results/schedules/can_steps_0.93.json

On held-out recorded calls (episodes from ``--first-episode``, default: past the table pruners'
training and validation episodes), with each call's recorded noise, every candidate schedule (the
searched compute steps and each single-step move of one of them by +-``--shifts``, all at the same
budget) is run and its action L1 to the dense action is taken per call. Reported:
  - the searched schedule's error;
  - the best candidate fixed for all calls;
  - the oracle that picks, per call, the candidate with the lowest error (it sees the dense answer,
    so no pruner can do better by choosing among these candidates);
  - both again with the choice made on one noise draw per call and scored on a second draw: a pruner
    sees the observation, not the sampling noise, so only this part of the oracle's gain is open to it.
If the oracle is barely below the best fixed candidate, a per-observation pruner has little to gain
over a static schedule here; if it is far below, the pruner is leaving accuracy on the table.
Writes ``results/robot/headroom_<task>_<schedule>.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, add_all_episodes_option, parse_args, provenance, write_json  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.static_search import steps_grid  # noqa: E402
from tts.trajectories import Windows, held_out_episodes  # noqa: E402


def neighbours(compute_steps: Sequence[int], steps: int, shifts: Sequence[int]) -> list[list[int]]:
    """``compute_steps`` first, then every schedule with one compute step (not step 0) moved by
    +-shift to a free step in (0, steps); each keeps the same number of compute steps."""
    base = sorted(compute_steps)
    out, seen = [base], {tuple(base)}
    for pos in range(1, len(base)):
        for d in [s * sign for s in shifts for sign in (-1, 1)]:
            new = base[pos] + d
            if 0 < new < steps and new not in base:
                cand = sorted(base[:pos] + [new] + base[pos + 1:])
                if tuple(cand) not in seen:
                    seen.add(tuple(cand))
                    out.append(cand)
    return out


def headroom(errors: torch.Tensor, errors_other_noise: torch.Tensor) -> dict:
    """``errors`` [candidates, calls] with the recorded noise (row 0: the searched schedule) and the
    same with another noise draw per call. Mean errors of the searched schedule, of the best fixed
    candidate and of the per-call oracle (both chosen and scored on the same draw), and the
    noise-honest versions: choices made on one draw scored on the other (averaged both ways). A
    pruner sees the observation, not the noise: a per-call preference it could learn must survive
    the new draw (one draw is a noisy guide, so this estimate of its gain is a conservative one)."""
    if errors.dim() != 2 or errors.shape != errors_other_noise.shape or errors.numel() == 0:
        raise ValueError(f"errors must be two equal [candidates, calls] tensors, got {tuple(errors.shape)} "
                         f"and {tuple(errors_other_noise.shape)}")
    per_candidate = errors.mean(1)
    best = int(per_candidate.argmin())
    oracle = errors.min(0)
    cols = torch.arange(errors.shape[1])

    def cross(choose: torch.Tensor, score: torch.Tensor) -> tuple[float, float]:
        fixed = float(score[int(choose.mean(1).argmin())].mean())
        return fixed, float(score[choose.argmin(0), cols].mean())

    (f1, o1), (f2, o2) = cross(errors, errors_other_noise), cross(errors_other_noise, errors)
    fixed_x, oracle_x = (f1 + f2) / 2, (o1 + o2) / 2
    return {"searched_error": float(per_candidate[0]), "best_fixed_error": float(per_candidate[best]),
            "best_fixed_candidate": best, "oracle_error": float(oracle.values.mean()),
            "oracle_gain_over_best_fixed": 1.0 - float(oracle.values.mean()) / float(per_candidate[best]),
            "searched_is_best_fraction": float((oracle.indices == 0).float().mean()),
            "cross_noise_best_fixed_error": fixed_x, "cross_noise_oracle_error": oracle_x,
            "cross_noise_oracle_gain_over_best_fixed": 1.0 - oracle_x / fixed_x}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--trajectories", type=Path, required=True)
    ap.add_argument("--schedule", type=Path, required=True, help="eval/search_static.py --objective output result")
    ap.add_argument("--first-episode", type=int, default=None,
                    help="first held-out episode (default: 96 for Lift, 89 for Can, as the table's pruners)")
    ap.add_argument("--calls", type=int, default=192, help="held-out calls used (evenly spread)")
    ap.add_argument("--shifts", default="1,2,4,8")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--out", type=Path, default=None)
    add_all_episodes_option(ap)
    args = parse_args(ap, argv)
    sched = json.loads(args.schedule.read_text())
    if "compute_steps" not in sched:
        raise ValueError(f"{args.schedule} holds no compute_steps (search it with --objective output)")
    first = args.first_episode if args.first_episode is not None else (89 if args.task == "can" else 96)
    every = args.all_episodes or sched.get("calibration_on") == "every recorded episode"  # as the search did
    held_out, n_episodes = held_out_episodes(args.trajectories, first, successful_only=not every)
    policy = load_policy(args.checkpoint)
    windows = Windows(policy, held_out)
    seeds = np.concatenate([e["noise_seed"] for e in held_out])
    pick = np.linspace(0, len(windows) - 1, min(args.calls, len(windows))).round().astype(int)
    steps, branches = policy.cfg.num_inference_steps, 3 * policy.model.config.n_layer

    def sample(offset: int) -> torch.Tensor:  # offset 0: the recorded noise; else another draw per call
        outs = []
        for s in range(0, len(pick), args.batch):
            idx = pick[s:s + args.batch]
            gen = [torch.Generator().manual_seed(int(x) + offset) for x in seeds[idx]]
            obs = windows.obs(idx)
            outs.append(policy.predict_action(obs, generator=gen)["action_pred"])
        return torch.cat(outs)

    offsets = (0, 1_000_003)
    with torch.no_grad():
        targets = [sample(o) for o in offsets]
        cands = neighbours(sched["compute_steps"], steps, [int(x) for x in args.shifts.split(",")])
        errs = [[], []]
        for cand in tqdm(cands, desc=f"{args.task} candidates"):
            plan = tts.plans.from_tensor(steps_grid(cand, steps, branches))
            with tts.accelerate(policy, ("timestep",), plan=plan):
                for e, o, t in zip(errs, offsets, targets):
                    e.append((sample(o) - t).abs().flatten(1).mean(1))
    res = headroom(torch.stack(errs[0]), torch.stack(errs[1]))
    res.update(task=args.task, schedule=str(args.schedule), compute_steps=sched["compute_steps"],
               candidates=len(cands), best_fixed_steps=cands[res["best_fixed_candidate"]], calls=len(pick),
               episodes=f"{first}..{n_episodes - 1}", trajectories=str(args.trajectories),
               provenance=provenance(seeds={"noise": "recorded per call"}))
    out = args.out or REPO / "results" / "robot" / f"headroom_{args.task}_{args.schedule.stem}.json"
    write_json(out, res)
    print(f"{args.task}: searched {res['searched_error']:.4f}, best fixed {res['best_fixed_error']:.4f}, "
          f"per-call oracle {res['oracle_error']:.4f} ({100 * res['oracle_gain_over_best_fixed']:.1f}% below best "
          f"fixed); chosen on one noise draw and scored on another: best fixed "
          f"{res['cross_noise_best_fixed_error']:.4f}, oracle {res['cross_noise_oracle_error']:.4f} "
          f"({100 * res['cross_noise_oracle_gain_over_best_fixed']:.1f}% below) over {len(cands)} candidates x "
          f"{len(pick)} held-out calls; wrote {out}")
    return res


if __name__ == "__main__":
    main()
