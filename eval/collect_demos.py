"""Scripted-expert demonstrations in robomimic's hdf5 layout.

    python eval/collect_demos.py --task lift --episodes 100 --seed 0 --out data/lift_expert.hdf5
    python eval/collect_demos.py --task can --episodes 200 --seed 0 --noise 0.3 --out data/can_expert_noisy.hdf5
    python eval/collect_demos.py --task square --episodes 100 --seed 0 --out data/square_expert.hdf5

Runs the waypoint expert on env seeds seed, seed+1, ...; keeps successful episodes (each stops a
few steps after the task succeeds, like robomimic's PH data) and writes them atomically, with the
expert's own success rate in ``results/experts/<task>_expert.json``. Training seeds (here 0..) and evaluation seeds
(eval/robot.py defaults to 100000..) are disjoint.

Mixed-quality, multimodal data in robomimic's MH proportions (6 operators: 2 better, 2 okay,
2 worse, 50 successful demos each; see eval/robot_suite/experts.py for the operators):

    python eval/collect_demos.py --task lift --mix mh --episodes 100 --seed 0 --out data/lift_mh.hdf5

Operator k attempts env seeds seed + k * episodes + (0 .. episodes-1); its success rate over
those seeds goes to ``results/experts/<task>_mh.json`` and its first ``--per-operator``
successes to the hdf5, with the filter keys robomimic's MH files have (``mask/better``,
``mask/okay``, ``mask/worse``, ``mask/okay_better``, ``mask/worse_better``, ``mask/worse_okay``
and one per operator, e.g. ``mask/better_operator_1``) and each demo's ``operator`` and
``quality`` attributes. Each finished operator is kept under ``<out>.parts/`` so an interrupted
run resumes where it stopped (parts are reused only for the same operator, seeds and expert code).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, provenance, write_json  # noqa: E402

from robot_suite import experts as experts_module  # noqa: E402
from robot_suite import pusht as pusht_module  # noqa: E402
from robot_suite.experts import EXPERT, EXPERTS, OPERATORS, Operator, make_expert  # noqa: E402
from robot_suite.robomimic import Demo, read_demos, write_demos  # noqa: E402
from robot_suite.tasks import TASKS, env_args, low_dim_obs, make_env, reset_env, sim_state  # noqa: E402

QUALITIES = ("better", "okay", "worse")


def run_expert(env, task: str, seed: int, extra_steps: int = 10, noise: float = 0.0,
               operator: Operator = EXPERT) -> tuple[bool, Demo]:
    """One expert episode; with ``noise`` > 0 the executed position command gets Gaussian noise of
    that std (action units) in the expert's ``noisy_phases`` while the clean command is recorded.
    An ``operator`` other than the plain expert acts in its own style (its own noise is recorded);
    its episode ends early if it gives up."""
    raw = reset_env(env, seed)
    op_rng = np.random.default_rng([seed, zlib.crc32(operator.name.encode())])
    expert = make_expert(task, env, operator, op_rng)
    rng = np.random.default_rng(seed + 7919)
    keys = TASKS[task].obs_keys
    obs = {k: [] for k in keys}
    actions, rewards, dones, states = [], [], [], []
    success_at = None
    for t in range(TASKS[task].horizon):
        lo = low_dim_obs(raw)
        for k in keys:
            obs[k].append(lo[k])
        states.append(sim_state(env, raw))
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
        if done or (expert.gave_up and success_at is None):
            break
    attrs = {"seed": seed, "noise": noise}
    if operator != EXPERT:
        attrs.update(operator=operator.name, quality=operator.quality, failed_grasps=expert.failed_grasps,
                     pauses=expert.pauses, gave_up=int(expert.gave_up))
    demo = Demo(obs={k: np.stack(v) for k, v in obs.items()}, actions=np.stack(actions),
                rewards=np.array(rewards), dones=np.array(dones), states=np.stack(states), attrs=attrs)
    return success_at is not None, demo


def _expert_code() -> str:
    files = (experts_module.__file__, pusht_module.__file__)
    return hashlib.sha1(b"".join(Path(f).read_bytes() for f in files)).hexdigest()[:12]


def _run_operator(env, task: str, op: Operator, seeds: list[int], keep: int, noise: float,
                  parts: Path, code: str) -> tuple[list[dict], list[Demo]]:
    """All of one operator's episodes (or its finished part from an earlier run of the same code)."""
    key = json.loads(json.dumps({"operator": op.params(), "seeds": seeds, "keep": keep, "noise": noise,
                                 "expert_code": code}))
    meta, h5 = parts / f"{op.name}.json", parts / f"{op.name}.hdf5"
    if meta.exists() and h5.exists():
        done = json.loads(meta.read_text())
        if done.get("key") == key:
            print(f"{op.name}: reusing {h5}")
            return done["outcomes"], read_demos(h5)
    outcomes, demos = [], []
    for s in tqdm(seeds, desc=f"{task} {op.name}"):
        ok, demo = run_expert(env, task, s, noise=noise, operator=op)
        outcomes.append({"seed": s, "success": ok, "steps": len(demo),
                         **{k: int(demo.attrs[k]) for k in ("failed_grasps", "pauses", "gave_up")}})
        if ok and len(demos) < keep:
            demos.append(demo)
    write_demos(h5, demos, env_args(task))
    write_json(meta, {"key": key, "outcomes": outcomes})
    return outcomes, demos


def collect_mh(args) -> None:
    ops = OPERATORS[args.task]
    parts = args.out.with_name(args.out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    prov = provenance(seeds=[args.seed, args.seed + len(ops) * args.episodes - 1])  # the code that runs
    code = _expert_code()
    env = make_env(args.task)
    demos, names_by, rows = [], {}, []
    for k, op in enumerate(ops):
        seeds = list(range(args.seed + k * args.episodes, args.seed + (k + 1) * args.episodes))
        outcomes, kept = _run_operator(env, args.task, op, seeds, args.per_operator, args.noise, parts, code)
        names = [f"demo_{len(demos) + i}" for i in range(len(kept))]
        demos.extend(kept)
        names_by.setdefault(op.quality, []).extend(names)
        names_by[op.name] = names
        ok = [o for o in outcomes if o["success"]]
        rows.append({
            "operator": op.name, "quality": op.quality, "params": op.params(),
            "seeds": [seeds[0], seeds[-1]], "attempts": len(outcomes), "successes": len(ok),
            "success_rate": len(ok) / len(outcomes), "gave_up": sum(o["gave_up"] for o in outcomes),
            "demos_kept": len(kept), "mean_demo_length": float(np.mean([len(d) for d in kept])) if kept else 0.0,
            "mean_failed_grasps_in_successes": float(np.mean([o["failed_grasps"] for o in ok])) if ok else 0.0,
            "mean_pauses_in_successes": float(np.mean([o["pauses"] for o in ok])) if ok else 0.0,
        })
        print(f"{op.name}: {len(ok)}/{len(outcomes)} successes, kept {len(kept)}")
    masks = {q: names_by.get(q, []) for q in QUALITIES}
    for a, b in (("okay", "better"), ("worse", "better"), ("worse", "okay")):  # robomimic's names
        masks[f"{a}_{b}"] = sorted(masks[a] + masks[b], key=lambda n: int(n.split("_")[1]))
    masks.update({op.name: names_by[op.name] for op in ops})
    write_demos(args.out, demos, env_args(args.task), masks=masks)
    report = {
        "provenance": prov,
        "task": args.task,
        "mix": "mh",
        "dart_noise": args.noise,
        "episodes_per_operator": args.episodes,
        "demos_per_operator": args.per_operator,
        "demos_written": len(demos),
        "masks": {k: len(v) for k, v in masks.items()},
        "operators": rows,
        "note": ("scripted operators in robomimic MH proportions (2 better, 2 okay, 2 worse); operator k used "
                 "env seeds seed + k * episodes_per_operator + (0..episodes_per_operator-1); success_rate is "
                 "over those seeds; failed demos are not kept. Far more regular than human operators."),
    }
    write_json(args.report or REPO / "results" / "experts" / f"{args.task}_mh.json", report)
    shutil.rmtree(parts)
    print(f"{args.task} mh: {len(demos)} demos from {len(ops)} operators; wrote {args.out}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=sorted(EXPERTS), required=True)
    ap.add_argument("--episodes", type=int, default=100, help="expert attempts (per operator with --mix)")
    ap.add_argument("--seed", type=int, default=0, help="first env seed")
    ap.add_argument("--noise", type=float, default=0.0,
                    help="DART-style noise std on executed position commands (clean actions are recorded)")
    ap.add_argument("--mix", choices=["mh"], default=None,
                    help="mh: the task's six operators in robomimic MH proportions instead of the one expert")
    ap.add_argument("--per-operator", type=int, default=50, help="successful demos kept per operator (--mix)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the simulation itself uses one core)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--report", type=Path, default=None,
                    help="success report (default: results/experts/<task>_expert.json, or <task>_mh.json with --mix)")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.mix == "mh":
        if args.task not in OPERATORS:
            ap.error(f"no operators for {args.task} yet; have {sorted(OPERATORS)}")
        return collect_mh(args)
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
