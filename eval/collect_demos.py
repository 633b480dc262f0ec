"""Scripted-expert demonstrations in robomimic's hdf5 layout.

    python eval/collect_demos.py --task lift --episodes 100 --seed 0 --out data/lift_expert.hdf5
    python eval/collect_demos.py --task can --episodes 200 --seed 0 --noise 0.3 --out data/can_expert_noisy.hdf5
    python eval/collect_demos.py --task square --episodes 100 --seed 0 --out data/square_expert.hdf5

Runs the waypoint expert on env seeds seed, seed+1, ...; keeps successful episodes (each stops a
few steps after the task succeeds, like robomimic's PH data) and writes them atomically, with the
expert's own success rate in ``results/experts/<task>_expert.json``. Training seeds (here 0..) and evaluation seeds
(eval/robot.py defaults to 100000..) are disjoint.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, provenance, write_json  # noqa: E402

from robot_suite.experts import EXPERTS  # noqa: E402
from robot_suite.robomimic import Demo, write_demos  # noqa: E402
from robot_suite.tasks import OBS_KEYS, TASKS, env_args, low_dim_obs, make_env, reset_env  # noqa: E402


def run_expert(env, task: str, seed: int, extra_steps: int = 10, noise: float = 0.0) -> tuple[bool, Demo]:
    """One expert episode; with ``noise`` > 0 the executed position command gets Gaussian noise of
    that std (action units) in the expert's ``noisy_phases`` while the clean command is recorded."""
    raw = reset_env(env, seed)
    expert = EXPERTS[task](env)
    rng = np.random.default_rng(seed + 7919)
    obs = {k: [] for k in OBS_KEYS}
    actions, rewards, dones, states = [], [], [], []
    success_at = None
    for t in range(TASKS[task].horizon):
        lo = low_dim_obs(raw)
        for k in OBS_KEYS:
            obs[k].append(lo[k])
        states.append(env.sim.get_state().flatten())
        a = expert.act(raw)
        executed = a.copy()
        if noise > 0 and expert.phase in expert.noisy_phases:
            executed[:3] = np.clip(executed[:3] + rng.normal(0.0, noise, 3), -1.0, 1.0)
        raw, r, _, _ = env.step(executed)
        success = bool(env._check_success())
        actions.append(a)
        rewards.append(float(success))
        if success and success_at is None:
            success_at = t
        done = success_at is not None and t >= success_at + extra_steps
        dones.append(int(done))
        if done:
            break
    demo = Demo(obs={k: np.stack(v) for k, v in obs.items()}, actions=np.stack(actions),
                rewards=np.array(rewards), dones=np.array(dones), states=np.stack(states),
                attrs={"seed": seed, "noise": noise})
    return success_at is not None, demo


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=sorted(EXPERTS), required=True)
    ap.add_argument("--episodes", type=int, default=100, help="expert attempts")
    ap.add_argument("--seed", type=int, default=0, help="first env seed")
    ap.add_argument("--noise", type=float, default=0.0,
                    help="DART-style noise std on executed position commands (clean actions are recorded)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the simulation itself uses one core)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--report", type=Path, default=None,
                    help="expert success report (default: results/experts/<task>_expert.json)")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    demos, outcomes = [], []
    env = make_env(args.task)
    for i in tqdm(range(args.episodes), desc=f"expert {args.task}"):
        ok, demo = run_expert(env, args.task, args.seed + i, noise=args.noise)
        outcomes.append(ok)
        if ok:
            demos.append(demo)
    write_demos(args.out, demos, env_args(args.task))
    report = {
        "provenance": provenance(seeds=list(range(args.seed, args.seed + args.episodes))),
        "task": args.task,
        "noise": args.noise,
        "expert_attempts": args.episodes,
        "expert_successes": int(sum(outcomes)),
        "expert_success_rate": float(np.mean(outcomes)),
        "demos_written": len(demos),
        "mean_demo_length": float(np.mean([len(d) for d in demos])) if demos else 0.0,
        "note": "scripted waypoint expert on true object poses: far more uniform than human demos",
    }
    write_json(args.report or REPO / "results" / "experts" / f"{args.task}_expert.json", report)
    print(f"expert {args.task}: {report['expert_successes']}/{args.episodes} successes; wrote {args.out}")


if __name__ == "__main__":
    main()
