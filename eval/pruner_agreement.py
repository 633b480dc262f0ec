"""How often a pruner's test-time decisions equal the schedule it started from (``--prior``).

    python eval/pruner_agreement.py --task lift --checkpoint checkpoints/lift_dpt \
        --pruner checkpoints/pruners/lift_tts_0.93 --trajectories data/trajectories/lift.pt --sparsity 0.93

Replays the recorded episodes the pruner was not trained on (index >= its ``n_train``: its
validation episodes, which only chose the epoch, and any later ones; or ``--first-episode``) in lockstep with their recorded noise through the pruner (exact budget with
``--sparsity``, else argmax) and compares every accelerated call's decisions [K, batch, branches]
with the prior grid of the pruner's metadata. The first call of an episode is dense (rollout
direction) and is left out. Writes ``results/robot/agreement_<task>_<pruner>.json``; eval/tables.py
renders it. If a pruner agrees with its prior everywhere, its success rate is the prior's.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, add_all_episodes_option, parse_args, provenance, write_json  # noqa: E402
from robot_suite.replay import replay  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402
from tts.trajectories import held_out_episodes  # noqa: E402
from tts.training import read_grid  # noqa: E402


def agreement(calls, prior: torch.Tensor, weights: Optional[list[torch.Tensor]] = None) -> dict:
    """Counts of accelerated calls / decisions equal to ``prior`` [K, nb] (dense calls skipped);
    ``weights`` (one [B] tensor per call, 0 for the padding of an episode that already ended in a
    lockstep replay) leaves out the padded samples."""
    n_calls = same_calls = n_dec = same_dec = 0
    for i, call in enumerate(calls):
        if call.dense:
            continue
        d = call.decisions()  # [K, B, nb]
        if d.shape[0] != prior.shape[0] or d.shape[2] != prior.shape[1]:
            raise ValueError(f"decisions {tuple(d.shape)} do not fit the prior grid {tuple(prior.shape)}")
        eq = d == prior[:, None, :]
        for b in range(d.shape[1]):
            if weights is not None and not weights[i][b]:
                continue
            n_calls += 1
            same_calls += int(eq[:, b].all())
            n_dec += eq[:, b].numel()
            same_dec += int(eq[:, b].sum())
    return {"calls": n_calls, "calls_identical": same_calls, "decisions": n_dec, "decisions_identical": same_dec,
            "calls_identical_fraction": same_calls / max(n_calls, 1),
            "decisions_identical_fraction": same_dec / max(n_dec, 1)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--pruner", type=Path, required=True)
    ap.add_argument("--trajectories", type=Path, required=True)
    ap.add_argument("--sparsity", type=float, default=None, help="exact-budget mode (default: argmax)")
    ap.add_argument("--first-episode", type=int, default=None,
                    help="first held-out episode (default: the pruner's n_train)")
    ap.add_argument("--batch", type=int, default=8, help="episodes replayed in lockstep")
    ap.add_argument("--out", type=Path, default=None)
    add_all_episodes_option(ap)
    args = parse_args(ap, argv)
    meta = json.loads(checkpoint_pair(args.pruner)[1].read_text())["metadata"]
    if not meta.get("prior"):
        raise ValueError(f"{args.pruner} was trained without --prior: nothing to compare with")
    first = args.first_episode
    if first is None:
        first = int(meta.get("n_train_episodes", meta["n_train"]))
    every = args.all_episodes or meta.get("all_episodes", False)  # the episodes the pruner was trained on
    held_out, n_episodes = held_out_episodes(args.trajectories, first, successful_only=not every)
    policy = load_policy(args.checkpoint)
    pruner = tts.load_pruner(args.pruner)
    calls, weights = [], []
    with tts.accelerate(policy, pruner.config.directions, pruner=pruner, sparsity=args.sparsity) as acc:
        for i in range(0, len(held_out), args.batch):
            acc.calls.clear()
            replay(policy, held_out[i:i + args.batch], lambda frame, _: weights.append(frame.weight))
            calls += acc.summary().calls
        prior = read_grid(meta["prior"], *calls[-1].decisions()[:, 0].shape, reuse=meta.get("prior_reuse"))
        res = agreement(calls, prior, weights)
    res.update(task=args.task, pruner=str(args.pruner), prior=meta["prior"], sparsity=args.sparsity,
               episodes=f"{first}..{n_episodes - 1}", trajectories=str(args.trajectories),
               provenance=provenance(seeds={"noise": "recorded per call"}))
    out = args.out or REPO / "results" / "robot" / f"agreement_{args.task}_{args.pruner.name}.json"
    write_json(out, res)
    print(f"{args.pruner.name}: {res['calls_identical']}/{res['calls']} held-out calls and "
          f"{100 * res['decisions_identical_fraction']:.1f}% of decisions equal the prior; wrote {out}")
    return res


if __name__ == "__main__":
    main()
