"""Success rate and policy-call speed of a Diffusion Policy on robosuite tasks.

    python eval/robot.py --task lift --checkpoint checkpoints/lift_dpt --method dense \
        --episodes 50 --seed 100000 [--n-envs 10] [--resume]
    python eval/robot.py ... --method uniform:0.93:timestep
    python eval/robot.py ... --method file:results/schedules/lift_steps_0.93.json
    python eval/robot.py ... --method pruner:checkpoints/pruners/lift_tts_0.93@0.93
    python eval/robot.py ... --method ddim:7          # or dpm:5, ddim:3:trailing, ddpm:10
    python eval/robot.py ... --method uniform:0.65:timestep+ddim:20   # TTS on a DDIM-20 base

``--method`` takes the vocabulary of both suites (eval/common/methods.py): dense | ddim:K[:SPACING] |
dpm:K | ddpm:K | uniform:RHO:DIRECTION | every_n:N:DIRECTION | file:SCHEDULE.json | pruner:PATH[@RHO] |
taylorseer:N:O, engine methods optionally on a base sampler (+ddim:K, +dpm:K).

Episodes run in waves of ``--n-envs`` environments whose observations are batched into one policy
call (batch = n_envs). Test seeds start at 100000, disjoint from the demonstration seeds. Every call
is timed; the JSON reports the median / p90 latency of a policy call (batch as run), calls/s
(= 1 / latency) and actions/s (= n_action_steps / latency per environment), realised sparsity and
MACs (dense vs realised, decoder branches + rest, profiled analytically; with a pruner, its MACs
are reported and added). One JSON per run (``results/robot/<task>_<method>_<first seed>.json``),
written atomically after each wave; ``--resume`` skips the seeds already finished (and the whole
run when every requested episode is in the file).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, parse_args, policy_slug, provenance, write_json  # noqa: E402
from common import methods  # noqa: E402
from common.methods import ROBOT_KINDS, VOCABULARY, Method, parse_method, pruner_weights_sha256  # noqa: E402

import tts  # noqa: E402
from tts.io import checkpoint_pair  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from robot_suite.rollout import make_policy_envs, policy_cameras, run_wave  # noqa: E402
from robot_suite.tasks import TASKS  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=sorted(TASKS), required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--method", default="dense", help=f"one of: {VOCABULARY}")
    ap.add_argument("--forecast", type=int, default=0,
                    help="Taylor forecast order for timestep reuse of file: / pruner: methods (0: plain reuse)")
    ap.add_argument("--horizon", type=int, default=None, help="env steps per episode (default: the task's; for smoke tests)")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--seed", type=int, default=100000, help="first test seed")
    ap.add_argument("--n-envs", type=int, default=10)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--trust-pickle", action="store_true", help="allow official .ckpt files (runs pickled code)")
    ap.add_argument("--obs-type", choices=["auto", "low_dim", "image"], default="auto",
                    help="the observations: image renders the policy's cameras (84x84 takes ~0.1 s per env step on "
                         "a CPU); auto (default) follows the checkpoint, and a mismatch is an error")
    args = parse_args(ap, argv)
    try:
        method = parse_method(args.method, kinds=ROBOT_KINDS, forecast=args.forecast)
    except ValueError as e:
        ap.error(str(e))
    torch.manual_seed(args.seed)
    label = method.label
    prefix = policy_slug(args.task, args.checkpoint)
    out = args.out or REPO / "results" / "robot" / f"{prefix}_{method.slug}_{args.seed}.json"
    seeds = list(range(args.seed, args.seed + args.episodes))
    done: dict[int, dict] = {}
    latencies: list[float] = []
    pruner_meta = _pruner_metadata(method)
    if args.resume and out.exists() and not _same_pruner(json.loads(out.read_text()).get("pruner_metadata"),
                                                         pruner_meta):
        print(f"{out} was run with other pruner weights (e.g. a training went on since): running it again")
    elif args.resume and out.exists():
        prev = json.loads(out.read_text())
        done = {e["seed"]: e for e in prev["episodes"]}
        latencies = prev.get("latencies_s", [])
        if all(s in done for s in seeds):
            print(f"[skip] {out}: all {len(seeds)} episodes done")
            return prev
        print(f"resuming: {len(done)} episodes already in {out}")

    policy = load_policy(args.checkpoint, trust_pickle=args.trust_pickle)
    acc = methods.install_policy(policy, method)
    image = bool(policy_cameras(policy))
    if args.obs_type != "auto" and args.obs_type != ("image" if image else "low_dim"):
        ap.error(f"--obs-type {args.obs_type}: {args.checkpoint} is {'an image' if image else 'a low-dim'} policy")
    args.obs_type = "image" if image else "low_dim"
    envs = make_policy_envs(policy, args.task, min(args.n_envs, len(seeds)))
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
            write_json(out, report(args, label, seeds, done, latencies, summary, policy, pruner_meta))
    res = report(args, label, seeds, done, latencies, summary or acc.summary(), policy, pruner_meta)
    write_json(out, res)
    print(f"{args.task} {label}: success {res['success_rate']:.3f} over {res['episodes_done']} episodes; "
          f"call latency median {res['latency_ms']['median']:.1f} ms (batch {res['batch']}); wrote {out}")
    return res


def _pruner_metadata(method: Method) -> Optional[dict]:
    """How the pruner of a ``pruner:`` run was trained (from its JSON), for the tables."""
    if method.kind != "pruner":
        return None
    meta = json.loads(checkpoint_pair(method.path)[1].read_text())
    keep = ("n_train_episodes", "sparsity", "paired", "loss_space", "static", "directions", "epochs", "git_sha",
            "command", "pruner_macs_per_call", "best_epoch", "prior")
    md = meta.get("metadata", {})
    return {"path": str(method.path), "config": meta["config"], "weights_sha256": pruner_weights_sha256(method),
            **({"epochs_done": len(md["history"])} if "history" in md else {}),
            **{k: v for k, v in md.items() if k in keep}}


def _training_note(checkpoint: Path) -> Optional[str]:
    """What the policy checkpoint says it was trained on (its ``metadata.note``), None when it says nothing."""
    meta_path = checkpoint_pair(checkpoint)[1]
    if Path(checkpoint).suffix == ".ckpt" or not meta_path.exists():
        return None
    return json.loads(meta_path.read_text()).get("metadata", {}).get("note")


def _same_pruner(prev: Optional[dict], now: Optional[dict]) -> bool:
    """Whether a result's pruner (its ``pruner_metadata``) is the one about to run: the same weights (or,
    for a result that predates the weights' digest, the same best epoch)."""
    if prev is None or now is None:
        return prev is now
    if "weights_sha256" in prev:
        return prev["weights_sha256"] == now["weights_sha256"]
    return prev.get("best_epoch") == now.get("best_epoch")


def report(args, label, seeds, done, latencies, summary, policy, pruner_meta: Optional[dict]) -> dict:
    eps = [done[s] for s in seeds if s in done]
    lat = np.array(latencies) if latencies else np.array([np.nan])
    med = float(np.median(lat))
    info = summary.to_dict() if summary is not None else {}
    return {
        "provenance": provenance(seeds=seeds),
        "task": args.task,
        "obs_type": args.obs_type,
        "checkpoint": str(args.checkpoint),
        "method": label,
        "episodes_requested": len(seeds),
        "episodes_done": len(eps),
        "success_rate": float(np.mean([e["success"] for e in eps])) if eps else float("nan"),
        "mean_max_coverage": (float(np.mean([e["max_coverage"] for e in eps]))
                              if eps and all("max_coverage" in e for e in eps) else None),
        "batch": min(args.n_envs, len(seeds)),
        "latency_ms": {"median": med * 1e3, "p90": float(np.percentile(lat, 90)) * 1e3, "calls": len(latencies)},
        "calls_per_s": 1.0 / med,
        "actions_per_s_per_env": policy.cfg.n_action_steps / med,
        "hz_definitions": "calls_per_s = 1 / median latency of one (batched) policy call; "
                          "actions_per_s_per_env = n_action_steps / median latency",
        "tts": info,
        "pruner_metadata": pruner_meta,  # read with the weights, before the first episode
        "episodes": eps,
        "latencies_s": latencies,
        "method_spec": args.method,
        "forecast": args.forecast,
        "policy_training_note": _training_note(args.checkpoint),
    }


if __name__ == "__main__":
    main()
