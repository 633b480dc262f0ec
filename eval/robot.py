"""Success rate and policy-call speed of a Diffusion Policy on robosuite tasks.

    python eval/robot.py --task lift --checkpoint checkpoints/lift_dpt --method dense \
        --episodes 50 --seed 100000 [--n-envs 10] [--resume]
    python eval/robot.py ... --method static --plan uniform:0.93:timestep
    python eval/robot.py ... --method tts --pruner checkpoints/lift_pruner [--sparsity 0.93]

Episodes run in waves of ``--n-envs`` environments whose observations are batched into one policy
call (batch = n_envs). Test seeds start at 100000, disjoint from the demonstration seeds. Every call
is timed; the JSON reports the median / p90 latency of a policy call (batch as run), calls/s
(= 1 / latency) and actions/s (= n_action_steps / latency per environment), realised sparsity and
MACs (dense vs realised, decoder branches + rest, profiled analytically; with a pruner, its MACs
are reported and added). ``--method tts`` runs a trained pruner: argmax decisions (the paper) or,
with ``--sparsity``, exactly that fraction reused per call (ranked by the pruner). One JSON per run,
written atomically after each wave; ``--resume`` skips the seeds already finished (and the whole
run when every requested episode is in the file).
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, provenance, write_json, parse_args  # noqa: E402

import tts  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.adapters.robosuite_tasks import OBS_KEYS, TASKS, low_dim_obs, make_env, reset_env  # noqa: E402


def parse_plan(spec: str) -> tuple[tuple[str, ...], "tts.plans.Plan"]:
    """``uniform:0.93:timestep`` | ``every_n:10:timestep`` | ``file:PATH`` (a searched schedule,
    eval/search_static.py) | ``dense`` -> (directions, plan)."""
    parts = spec.split(":")
    if parts[0] == "file" and len(parts) == 2:
        doc = json.loads(Path(parts[1]).read_text())
        return tuple(doc["directions"]), tts.plans.from_tensor(doc["grid"])
    if parts[0] == "dense":
        return ("forward", "timestep", "rollout"), tts.plans.dense()
    if parts[0] == "uniform" and len(parts) == 3:
        return (parts[2],), tts.plans.uniform(float(parts[1]), parts[2])
    if parts[0] == "every_n" and len(parts) == 3:
        return (parts[2],), tts.plans.every_n(int(parts[1]), parts[2])
    raise ValueError(f"unknown plan {spec!r}; use dense, uniform:<sparsity>:<direction>, every_n:<n>:<direction> "
                     "or file:<path>")


def noise_seed(episode_seed: int, call: int) -> int:
    """Seed of the sampling noise of one policy call of one episode (recorded trajectories)."""
    return episode_seed * 1000 + call


def method_label(args) -> str:
    label = _base_label(args)
    forecast = getattr(args, "forecast", 0)
    return label + (f"-taylor{forecast}" if forecast else "")


def _base_label(args) -> str:
    if args.method == "dense":
        return "dense"
    if args.method == "ddim":
        return f"ddim{args.steps}"
    if args.method == "static":
        plan = Path(args.plan.split(":", 1)[1]).stem if args.plan.startswith("file:") else args.plan.replace(":", "-")
        return f"static-{plan}"
    if args.pruner is None:
        raise SystemExit("--method tts needs --pruner PATH (train one with eval/train_pruner.py)")
    return f"tts-{args.pruner.name}" + ("" if args.sparsity is None else f"-budget{args.sparsity:g}")


def accelerate(policy, args) -> "tts.Accelerator":
    """The method of ``args`` installed on ``policy`` (dense: a dense plan, bit-identical, gives MACs)."""
    forecast = getattr(args, "forecast", 0)
    if args.method == "tts":
        pruner = tts.load_pruner(args.pruner)
        trained = int(getattr(pruner, "metadata", {}).get("forecast", 0) or 0)
        if trained != forecast:
            raise SystemExit(f"{args.pruner} was trained with --forecast {trained}; evaluate it with the same")
        parallel = {"auto": "auto", "on": True, "off": False}[getattr(args, "parallel", "auto")]
        return tts.accelerate(policy, pruner.config.directions, pruner=pruner, sparsity=args.sparsity,
                              forecast=forecast, parallel=parallel)
    if args.method == "ddim":
        policy.set_sampler("ddim", args.steps)
    directions, plan = parse_plan(args.plan if args.method == "static" else "dense")
    return tts.accelerate(policy, directions, plan=plan, forecast=forecast if "timestep" in directions else 0)


def run_wave(policy, envs, seeds, task, generator, record: bool = False,
             horizon: Optional[int] = None) -> tuple[list[dict], list[float]]:
    """Run one episode per env in lockstep; returns per-episode outcomes and per-call latencies.

    ``record=True``: every env gets its own noise generator per call (seeded by :func:`noise_seed`,
    so a sample's noise does not depend on the batch) and each outcome carries its trajectory: the
    obs window fed to the policy [R, To, obs_dim], the dense ``action_pred`` [R, H, Da], the
    executed chunk [R, Ta, Da] and the noise seeds [R] (R = calls until success or the horizon).
    """
    cfg = policy.cfg
    n = len(seeds)
    policy.reset()
    raws = [reset_env(env, s) for env, s in zip(envs[:n], seeds)]
    hist = [collections.deque([low_dim_obs(r)] * cfg.n_obs_steps, maxlen=cfg.n_obs_steps) for r in raws]
    success = [False] * n
    steps = [0] * n
    traj = [{"obs": [], "action_pred": [], "action": [], "noise_seed": []} for _ in range(n)]
    latencies = []
    horizon = horizon or TASKS[task].horizon
    t = 0
    call = 0
    while t < horizon and not all(success):
        obs = {k: np.stack([np.stack([h[j][k] for j in range(cfg.n_obs_steps)]) for h in hist]) for k in OBS_KEYS}
        gen = [torch.Generator().manual_seed(noise_seed(s, call)) for s in seeds] if record else generator
        t0 = time.perf_counter()
        out = policy.predict_action(obs, generator=gen)
        latencies.append(time.perf_counter() - t0)
        actions = out["action"].cpu().numpy()
        if record:
            window = policy.obs_vector(obs).cpu().numpy()
            for e in range(n):
                if not success[e]:
                    for key, val in (("obs", window[e]), ("action_pred", out["action_pred"][e].cpu().numpy()),
                                     ("action", actions[e]), ("noise_seed", noise_seed(seeds[e], call))):
                        traj[e][key].append(val)
        for a_i in range(actions.shape[1]):
            for e in range(n):
                if success[e]:
                    continue  # finished envs keep their last observation (batch size stays constant)
                raw, _, _, _ = envs[e].step(actions[e, a_i])
                hist[e].append(low_dim_obs(raw))
                steps[e] += 1
                if envs[e]._check_success():
                    success[e] = True
            t += 1
            if t >= horizon or all(success):
                break
        call += 1
    outcomes = [{"seed": s, "success": bool(ok), "env_steps": st} for s, ok, st in zip(seeds, success, steps)]
    if record:
        for o, tr in zip(outcomes, traj):
            o["trajectory"] = {k: np.stack(v) for k, v in tr.items()}
    return outcomes, latencies


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=sorted(TASKS), required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--method", choices=["dense", "static", "tts", "ddim"], default="dense",
                    help="ddim: the fewer-steps baseline (DDIM with --steps, dense)")
    ap.add_argument("--steps", type=int, default=10, help="for --method ddim")
    ap.add_argument("--plan", default="uniform:0.93:timestep", help="for --method static")
    ap.add_argument("--pruner", type=Path, default=None, help="for --method tts: a trained pruner (eval/train_pruner.py)")
    ap.add_argument("--sparsity", type=float, default=None,
                    help="for --method tts: exact-budget mode at this sparsity (default: the pruner's argmax)")
    ap.add_argument("--forecast", type=int, default=0,
                    help="TaylorSeer-style forecast order for timestep reuse (0: plain reuse)")
    ap.add_argument("--horizon", type=int, default=None, help="env steps per episode (default: the task's; for smoke tests)")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--seed", type=int, default=100000, help="first test seed")
    ap.add_argument("--n-envs", type=int, default=10)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--trust-pickle", action="store_true", help="allow official .ckpt files (runs pickled code)")
    args = parse_args(ap, argv)
    torch.manual_seed(args.seed)
    label = method_label(args)
    out = args.out or REPO / "results" / "robot" / f"{args.task}_{label}_{args.seed}.json"
    seeds = list(range(args.seed, args.seed + args.episodes))
    done: dict[int, dict] = {}
    latencies: list[float] = []
    if args.resume and out.exists():
        prev = json.loads(out.read_text())
        done = {e["seed"]: e for e in prev["episodes"]}
        latencies = prev.get("latencies_s", [])
        if all(s in done for s in seeds):
            print(f"[skip] {out}: all {len(seeds)} episodes done")
            return prev
        print(f"resuming: {len(done)} episodes already in {out}")

    policy = load_policy(args.checkpoint, trust_pickle=args.trust_pickle)
    acc = accelerate(policy, args)
    envs = [make_env(args.task) for _ in range(min(args.n_envs, len(seeds)))]
    todo = [s for s in seeds if s not in done]
    generator = torch.Generator().manual_seed(args.seed)
    summary = None
    with tqdm(total=len(seeds), initial=len(done), desc=f"{args.task} {label}") as bar:
        for w in range(0, len(todo), len(envs)):
            wave = todo[w:w + len(envs)]
            outcomes, lat = run_wave(policy, envs, wave, args.task, generator, horizon=args.horizon)
            latencies += lat
            for o in outcomes:
                done[o["seed"]] = o
            bar.update(len(wave))
            bar.set_postfix(success=f"{np.mean([e['success'] for e in done.values()]):.2f}")
            summary = acc.summary()
            write_json(out, report(args, label, seeds, done, latencies, summary, policy))
    res = report(args, label, seeds, done, latencies, summary or acc.summary(), policy)
    write_json(out, res)
    print(f"{args.task} {label}: success {res['success_rate']:.3f} over {res['episodes_done']} episodes; "
          f"call latency median {res['latency_ms']['median']:.1f} ms (batch {res['batch']}); wrote {out}")
    return res


def _pruner_metadata(args) -> Optional[dict]:
    """How the pruner of a ``--method tts`` run was trained (from its JSON), for the tables."""
    if args.method != "tts":
        return None
    meta = json.loads(checkpoint_pair(args.pruner)[1].read_text())
    keep = ("n_train_episodes", "sparsity", "paired", "loss_space", "static", "directions", "epochs", "git_sha",
            "command", "pruner_macs_per_call", "best_epoch")
    return {"path": str(args.pruner), "config": meta["config"],
            **{k: v for k, v in meta.get("metadata", {}).items() if k in keep}}


def report(args, label, seeds, done, latencies, summary, policy) -> dict:
    eps = [done[s] for s in seeds if s in done]
    lat = np.array(latencies) if latencies else np.array([np.nan])
    med = float(np.median(lat))
    info = summary.to_dict() if summary is not None else {}
    return {
        "provenance": provenance(seeds=seeds),
        "task": args.task,
        "checkpoint": str(args.checkpoint),
        "method": label,
        "episodes_requested": len(seeds),
        "episodes_done": len(eps),
        "success_rate": float(np.mean([e["success"] for e in eps])) if eps else float("nan"),
        "batch": min(args.n_envs, len(seeds)),
        "latency_ms": {"median": med * 1e3, "p90": float(np.percentile(lat, 90)) * 1e3, "calls": len(latencies)},
        "calls_per_s": 1.0 / med,
        "actions_per_s_per_env": policy.cfg.n_action_steps / med,
        "hz_definitions": "calls_per_s = 1 / median latency of one (batched) policy call; "
                          "actions_per_s_per_env = n_action_steps / median latency",
        "tts": info,
        "pruner_metadata": _pruner_metadata(args),
        "episodes": eps,
        "latencies_s": latencies,
        "note": "policy trained on scripted-expert demonstrations (uniform, not human data)",
    }


if __name__ == "__main__":
    main()
