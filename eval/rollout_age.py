"""How old the reused rollout features are: the age, in policy calls, of every reused rollout slot.

    python eval/rollout_age.py --task lift --checkpoint checkpoints/lift_dpt \
        --trajectories data/trajectories/lift.pt --methods uniform:0.93:rollout rotating:0.93:rollout ...

The rollout cache writes a (step, branch) slot only when it computes, so a reused slot holds the
output of the last call that computed it, not necessarily the previous call's. Each method replays
held-out recorded episodes (index >= ``--first-episode``, past the pruners' training and validation
sets) one episode at a time with their recorded observations and noise, and
``Summary.rollout_ages`` gives the age of every rollout decision (1 = the previous call's output).
Writes ``results/robot/rollout_age_<policy>.json``, one entry per method, merged with earlier runs
(``<policy>``: the task, plus the checkpoint's name unless it is the bundled one).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, add_all_episodes_option, add_replay_options, parse_args, policy_slug, provenance, write_json  # noqa: E402
from common.methods import ROBOT_KINDS, install, parse_method  # noqa: E402
from robot_suite.replay import replay  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.trajectories import held_out_episodes  # noqa: E402


def ages_of(policy, method, episodes) -> dict:
    """Rollout-age statistics of ``method`` over ``episodes`` (each replayed as its own episode)."""
    ages = []
    with install(policy, method) as acc:
        for ep in tqdm(episodes, desc=method.label, leave=False):
            start = len(acc.calls)
            replay(policy, [ep])
            ages.append(acc.summary().rollout_ages(acc.calls[start:]))
        summary = acc.summary()
    a = torch.cat(ages)
    stats = {"reused_slots": int(a.numel())}
    if a.numel():
        counts = torch.bincount(a)
        stats.update(mean_calls=float(a.float().mean()), median_calls=float(a.float().median()),
                     max_calls=int(a.max()), fraction_previous_call=float((a == 1).float().mean()),
                     histogram={int(i): int(c) for i, c in enumerate(counts.tolist()) if c})
    stats.update(sparsity=summary.sparsity([c for c in summary.calls if not c.dense]), plan=summary.plan,
                 calls=sum(len(ep["obs"]) for ep in episodes))
    return stats


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_replay_options(ap)
    ap.add_argument("--first-episode", type=int, default=None,
                    help="first held-out episode (default: 96 for Lift, 89 for Can, as the table's pruners)")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--out", type=Path, default=None)
    add_all_episodes_option(ap)
    args = parse_args(ap, argv)
    methods = [parse_method(m, kinds=ROBOT_KINDS) for m in args.methods]
    first = args.first_episode if args.first_episode is not None else (89 if args.task == "can" else 96)
    episodes, _ = held_out_episodes(args.trajectories, first, successful_only=not args.all_episodes)
    episodes = episodes[:args.episodes]
    policy = load_policy(args.checkpoint)
    out = args.out or REPO / "results" / "robot" / f"rollout_age_{policy_slug(args.task, args.checkpoint)}.json"
    res = json.loads(out.read_text()) if out.exists() else {"task": args.task, "methods": {}}
    for method in methods:
        stats = ages_of(policy, method, episodes)
        stats["provenance"] = provenance(seeds={"episodes": f"{first}..{first + len(episodes) - 1}",
                                                "noise": "recorded per call"})
        res["methods"][method.label] = stats
        write_json(out, res)
        print(f"{args.task} {method.label}: {stats.get('mean_calls', float('nan')):.1f} calls old on average, "
              f"{100 * stats.get('fraction_previous_call', 0):.0f}% from the previous call "
              f"({stats['reused_slots']} reused slots)")
    res.update(trajectories=str(args.trajectories), checkpoint=str(args.checkpoint))
    write_json(out, res)
    return res


if __name__ == "__main__":
    main()
