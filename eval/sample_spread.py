"""How much a method's actions vary with the sampling noise, and how close they stay to the dense policy's.

    python eval/sample_spread.py --task pusht --checkpoint checkpoints/pusht_mh_dpt_17k \
        --trajectories data/trajectories/pusht-pusht_mh_dpt_17k_full.pt --all-episodes \
        --methods dense dpm:7 file:results/schedules/pusht-pusht_mh_dpt_17k_steps_0.93.json \
        pruner:checkpoints/pruners/pusht-pusht_mh_dpt_17k_reference_forward-timestep-rollout_0.93

A policy trained on multimodal demonstrations should return different actions for different noise
draws (one mode or another). An L1 to a dense action drawn with *other* noise, the loss the
reference trains its pruner with, is smallest for an action between the modes: a method can lower it
by collapsing its samples towards the conditional mean, which a closed-loop task may not survive.
Each method replays the held-out recorded episodes (index >= ``--first-episode``, default 96: the
reference pruners' validation episodes) in lockstep, ``--draws`` times, draw 0 with each call's
recorded noise and draw d with the recorded seed + d * 1000003, and reports on the normalised
actions (every dimension on the policy's [-1, 1] scale), over every call but each episode's first:
  - ``spread``: the mean absolute deviation of the draws around their per-call mean;
  - ``l1_same_draw``: the L1 of draw 0 to the recorded dense action (the same noise);
  - ``l1_other_draw``: the L1 of draws 1.. to the recorded dense action (other noise: what an
    unpaired training loss measures; the dense policy's own value is what a second draw costs).
Writes ``results/robot/sample_spread_<policy>.json``, one entry per method with its own provenance
(``--resume`` keeps the entries measured on the same episodes and draws and adds the others).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, add_all_episodes_option, add_replay_options, parse_args, policy_slug, provenance, write_json  # noqa: E402
from common.methods import ROBOT_KINDS, Method, install_policy, parse_method, pruner_weights_sha256  # noqa: E402
from robot_suite.replay import replay  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.trajectories import held_out_episodes  # noqa: E402

DRAW_OFFSET = 1_000_003  # seed offset between two noise draws of the same call


def spread_stats(draws: torch.Tensor, target: torch.Tensor) -> dict:
    """``draws`` [D, N, ...] (D >= 2 samples of N calls, draw 0 with the recorded noise) against
    ``target`` [N, ...] (the recorded dense actions): spread and L1s as in the module docstring."""
    if draws.dim() < 2 or draws.shape[0] < 2 or draws.shape[1:] != target.shape or target.shape[0] == 0:
        raise ValueError(f"need draws [D >= 2, N, ...] and a target [N, ...] of the same calls, got "
                         f"{tuple(draws.shape)} and {tuple(target.shape)}")
    dev = (draws - draws.mean(0)).abs().flatten(2).mean(2)  # [D, N]
    same = (draws[0] - target).abs().flatten(1).mean(1)
    other = (draws[1:] - target).abs().flatten(2).mean(2)
    return {"spread": float(dev.mean()), "l1_same_draw": float(same.mean()), "l1_other_draw": float(other.mean()),
            "calls": int(target.shape[0]), "draws": int(draws.shape[0])}


def sample_draws(policy, method: Method, episodes: Sequence[dict], draws: int,
                 batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised actions [draws, N, H, Da] of ``method`` on every call but the first of each
    episode, and the recorded dense actions [N, H, Da] of the same calls."""
    base = (policy.cfg.scheduler, policy.cfg.num_inference_steps, policy.cfg.timestep_spacing)
    outs: list[list[torch.Tensor]] = [[] for _ in range(draws)]
    target: list[torch.Tensor] = []
    norm = policy.action_normalizer.normalize
    try:
        with install_policy(policy, method), torch.no_grad():
            for d in tqdm(range(draws), desc=method.label, leave=False):
                for i in range(0, len(episodes), batch):
                    def keep(frame, out, d=d):
                        if frame.first:
                            return
                        real = frame.weight.bool()
                        outs[d].append(norm(out["action_pred"][real].float()).cpu())
                        if d == 0:
                            target.append(norm(frame.data["action_pred"][real].float().to(policy.device)).cpu())
                    replay(policy, episodes[i:i + batch], keep, noise_offset=d * DRAW_OFFSET)
    finally:
        policy.set_sampler(*base)
    return torch.stack([torch.cat(o) for o in outs]), torch.cat(target)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_replay_options(ap)
    ap.add_argument("--first-episode", type=int, default=96, help="first held-out episode")
    ap.add_argument("--draws", type=int, default=4, help="noise draws per call (at least 2)")
    ap.add_argument("--batch", type=int, default=16, help="episodes replayed in lockstep")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true",
                    help="keep the methods the output already holds (measured on the same episodes and draws) "
                         "and measure only the others")
    add_all_episodes_option(ap)
    args = parse_args(ap, argv)
    if args.draws < 2:
        ap.error("--draws must be at least 2 (one draw has no spread)")
    methods = [parse_method(m, kinds=ROBOT_KINDS) for m in args.methods]
    episodes, n_episodes = held_out_episodes(args.trajectories, args.first_episode,
                                             successful_only=not args.all_episodes)
    policy = load_policy(args.checkpoint)
    out = args.out or REPO / "results" / "robot" / f"sample_spread_{policy_slug(args.task, args.checkpoint)}.json"
    setup = {"task": args.task, "checkpoint": str(args.checkpoint), "trajectories": str(args.trajectories),
             "episodes": f"{args.first_episode}..{n_episodes - 1}", "draws": args.draws, "action_space": "normalised"}
    res = json.loads(out.read_text()) if args.resume and out.exists() else {}
    if any(res.get(k) != v for k, v in setup.items()):  # another set-up: its methods do not compare
        res = {**setup, "methods": {}}
    for method in methods:
        weights = pruner_weights_sha256(method)
        kept = res["methods"].get(method.label)
        if kept is not None and kept.get("weights_sha256", weights) == weights:
            print(f"{args.task} {method.label}: measured already ({out})")
            continue
        if kept is not None:
            print(f"{args.task} {method.label}: measured with other pruner weights, measuring again")
        stats = spread_stats(*sample_draws(policy, method, episodes, args.draws, args.batch))
        if weights is not None:
            stats["weights_sha256"] = weights
        stats["provenance"] = provenance(seeds={"noise": f"recorded seed + d * {DRAW_OFFSET}, d = 0..{args.draws - 1}"})
        res["methods"][method.label] = stats
        write_json(out, res)  # a method at a time: an interrupted run keeps what it measured
        print(f"{args.task} {method.label}: spread {stats['spread']:.4f}, L1 to dense on the same draw "
              f"{stats['l1_same_draw']:.4f}, on another draw {stats['l1_other_draw']:.4f} ({stats['calls']} calls)")
    return res


if __name__ == "__main__":
    main()
