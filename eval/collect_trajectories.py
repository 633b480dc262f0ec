"""Dense-policy trajectories for pruner training (the pruner's target is the dense policy's action).

    python eval/collect_trajectories.py --task lift --checkpoint checkpoints/lift_dpt \
        --episodes 112 --seed 200000 --out data/trajectories/lift.pt

Runs the dense policy in the env (waves of ``--n-envs`` batched envs) and stores, per policy call,
the exact obs window fed to ``predict_action`` [To, obs_dim], the dense ``action_pred`` [H, Da] (the
training target), the executed chunk [Ta, Da] and the noise seed of that call (so a paired-noise
trainer can replay the same noise). Episodes keep their success flag; the trainer uses the
successful ones. Seeds 200000.. are disjoint from demonstrations (0..) and test episodes (100000..).
The file is rewritten atomically after every wave; ``--resume`` continues after an interruption.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import provenance, parse_args  # noqa: E402
from robot_suite.rollout import make_policy_envs, run_wave  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from robot_suite.tasks import TASKS  # noqa: E402
from tts.trajectories import load_trajectories, save_trajectories  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=sorted(TASKS), required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--episodes", type=int, default=112)
    ap.add_argument("--seed", type=int, default=200000)
    ap.add_argument("--n-envs", type=int, default=16)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--horizon", type=int, default=None, help="env steps per episode (default: the task's; for smoke tests)")
    ap.add_argument("--full-horizon", action="store_true",
                    help="run every episode to the task's horizon and record the frames after success too "
                         "(the reference's pruner training data)")
    args = parse_args(ap, argv)
    seeds = list(range(args.seed, args.seed + args.episodes))
    episodes: list[dict] = []
    if args.resume and args.out.exists():
        episodes, _ = load_trajectories(args.out, successful_only=False)
        print(f"resuming: {len(episodes)} episodes already in {args.out}")
    done = {e["seed"] for e in episodes}
    policy = load_policy(args.checkpoint)
    meta = provenance(seeds=seeds)
    meta.update(task=args.task, checkpoint=str(args.checkpoint), policy_config=policy.cfg.__dict__)
    envs = make_policy_envs(policy, args.task, min(args.n_envs, len(seeds)))  # cameras for an image policy
    todo = [s for s in seeds if s not in done]
    with tqdm(total=len(seeds), initial=len(done), desc=f"trajectories {args.task}") as bar:
        for w in range(0, len(todo), len(envs)):
            wave = todo[w:w + len(envs)]
            outcomes, _ = run_wave(policy, envs, wave, args.task, None, record=True, horizon=args.horizon,
                                   full_horizon=args.full_horizon)
            for o in outcomes:
                episodes.append({"seed": o["seed"], "success": o["success"], **o["trajectory"]})
            save_trajectories(args.out, episodes, meta)
            bar.update(len(wave))
            bar.set_postfix(success=f"{np.mean([e['success'] for e in episodes]):.2f}")
    ok = sum(e["success"] for e in episodes)
    print(f"{args.task}: {ok}/{len(episodes)} successful dense episodes; wrote {args.out}")


if __name__ == "__main__":
    main()
