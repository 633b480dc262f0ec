"""Train a TTS pruner on dense-policy trajectories (spec §4), on CPU.

    python eval/train_pruner.py --trajectories data/trajectories/lift.pt --checkpoint checkpoints/lift_dpt \
        --out checkpoints/lift_pruner --sparsity 0.93 --n-train 32 --n-val 16 --epochs 6

Episode groups of ``--batch`` run in lockstep, one optimizer step per policy call (frame): frame 0
is the dense call that fills the rollout cache and is excluded from the loss; every later frame runs
the full K-step sampler with straight-through gates (all branches computed and mixed, gradients
into the pruner only; the policy is frozen) and minimises L1(sparse action_pred, dense action_pred)
+ lambda * |reuse fraction - sparsity| per sample. ``--paired`` replays each frame's recorded noise
seed, so the sparse sample is compared with the same draw the dense policy made (spec §10 item 13);
the default, like the paper, uses fresh noise. Validation uses test-time argmax decisions. The best
epoch (validation L1 + lambda * |sparsity error|) is written as ``<out>.safetensors/.json``; state is
saved every epoch under ``runs/<out name>/`` and ``--resume`` continues from it.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from collect_trajectories import load_trajectories  # noqa: E402
from common import provenance, parse_args  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.io import atomic_path  # noqa: E402
from tts.pruner import PrunerConfig, PrunerPlan, build_pruner, distill_schedule, pruner_loss, save_pruner  # noqa: E402
from tts.trajectories import episode_groups, lockstep_frames, split_episodes  # noqa: E402

KEYS = ("obs", "action_pred", "noise_seed")


def obs_dict(policy, window: torch.Tensor) -> dict[str, np.ndarray]:
    """Split a stored obs window [E, To, obs_dim] back into the policy's observation keys."""
    out, i = {}, 0
    for k, d in zip(policy.cfg.obs_keys, policy.cfg.obs_dims):
        out[k] = window[..., i:i + d].numpy()
        i += d
    return out


def generators(frame, paired: bool, rng: torch.Generator) -> list[torch.Generator]:
    seeds = frame.data["noise_seed"].tolist() if paired else torch.randint(0, 2**62, (len(frame.weight),), generator=rng).tolist()
    return [torch.Generator().manual_seed(int(s)) for s in seeds]


def run_group(policy, plan: PrunerPlan, group, args, rng, opt=None) -> dict[str, float]:
    """One episode group in lockstep; trains when ``opt`` is given. Returns weighted means."""
    policy.reset()
    sums = {"l1": 0.0, "sparsity": 0.0, "n": 0.0}
    for frame in lockstep_frames(group, KEYS):
        obs = obs_dict(policy, frame.data["obs"])
        gen = generators(frame, args.paired, rng)
        target = frame.data["action_pred"].float()
        if args.loss_space == "normalized":  # every action dim on the same [-1, 1] scale (spec §10 item 14)
            target = policy.action_normalizer.normalize(target)
        if frame.first:
            policy.predict_action(obs, generator=gen)  # dense: fills the rollout cache
            continue
        w = frame.weight
        if opt is not None:
            pred = policy.predict_action(obs, generator=gen, enable_grad=True)["action_pred"]
            if args.loss_space == "normalized":
                pred = policy.action_normalizer.normalize(pred)
            out = pruner_loss(pred, target, plan.gates, args.sparsity, args.lam, w)
            opt.zero_grad(set_to_none=True)
            out["loss"].backward()
            torch.nn.utils.clip_grad_norm_(plan.pruner.parameters(), 1.0)
            opt.step()
            l1 = float(out["l1"].detach())
            reuse = out["reuse"].detach()
        else:
            pred = policy.predict_action(obs, generator=gen)["action_pred"]
            if args.loss_space == "normalized":
                pred = policy.action_normalizer.normalize(pred)
            l1 = float(((pred - target).abs().reshape(len(w), -1).mean(1) * w).sum() / w.sum().clamp_min(1))
            reuse = (plan.last_codes[:, :] != 0).float().mean((1, 2))
        n = float(w.sum())
        sums["l1"] += l1 * n
        sums["sparsity"] += float((reuse * w).sum())
        sums["n"] += n
    n = max(sums["n"], 1.0)
    return {"l1": sums["l1"] / n, "sparsity": sums["sparsity"] / n, "frames": sums["n"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectories", type=Path, required=True)
    ap.add_argument("--checkpoint", type=Path, required=True, help="the (frozen) policy")
    ap.add_argument("--out", type=Path, required=True, help="pruner path without suffix")
    ap.add_argument("--directions", default="forward,timestep,rollout")
    ap.add_argument("--sparsity", type=float, default=0.93)
    ap.add_argument("--lam", type=float, default=1.0, help="weight of the sparsity term")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--batch", type=int, default=16, help="episodes per lockstep group")
    ap.add_argument("--n-train", type=int, default=32)
    ap.add_argument("--n-val", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--weight-decay", type=float, default=1e-4)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--paired", action="store_true", help="replay the dense call's noise (paired target)")
    ap.add_argument("--loss-space", choices=["raw", "normalized"], default="raw",
                    help="L1 on raw actions (the paper) or on the policy's normalised actions")
    ap.add_argument("--static", action="store_true",
                    help="train a static router instead (Learning-to-Cache-style baseline: one decision per "
                         "step x branch, not per observation)")
    ap.add_argument("--forecast", type=int, default=0,
                    help="train (and validate) with TaylorSeer-style forecasting timestep reuse of this order; "
                         "use the same --forecast at test time")
    ap.add_argument("--prior", type=Path, default=None,
                    help="a searched static schedule (eval/search_static.py JSON) whose decisions become fixed "
                         "prior logits; the pruner (head zero-initialised) learns per-observation corrections")
    ap.add_argument("--init-schedule", type=Path, default=None,
                    help="warm start: fit the pruner to a searched static schedule (eval/search_static.py JSON) "
                         "by cross-entropy before the straight-through training")
    ap.add_argument("--val-mode", choices=["argmax", "budget"], default="argmax",
                    help="test-time rule used for validation and checkpoint selection (budget: exactly --sparsity)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")
    args = parse_args(ap, argv)
    tts.plans.check_sparsity(args.sparsity)
    directions = tts.plans.check_directions(args.directions.split(","))
    torch.manual_seed(args.seed)

    episodes, traj_meta = load_trajectories(args.trajectories)
    train, val = split_episodes(episodes, args.n_train, args.n_val)
    policy = load_policy(args.checkpoint).requires_grad_(False)
    cfg = policy.model.config
    pruner = build_pruner(PrunerConfig(
        memory_dim=cfg.n_emb, num_branches=3 * cfg.n_layer, directions=directions, hidden=args.hidden,
        kind="static" if args.static else "transformer", steps=policy.cfg.num_inference_steps,
        prior=args.prior is not None))
    if args.prior is not None:
        pruner.set_prior(tts.plans.from_tensor(json.loads(args.prior.read_text())["grid"]).decisions[0])
    train_plan = PrunerPlan(pruner, mode="ste")
    opt = torch.optim.AdamW(pruner.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    groups_per_epoch = math.ceil(len(train) / args.batch)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda e: min(1.0, (e + 1) / max(1, args.epochs // 5)) * 0.5 * (1 + math.cos(math.pi * e / args.epochs)))
    run_dir = args.run_dir or Path("runs") / args.out.name
    state_path = run_dir / "pruner_state.pt"
    epoch, history, best, best_state = 0, [], None, None
    if args.resume and state_path.exists():
        st = torch.load(state_path, map_location="cpu", weights_only=False)
        pruner.load_state_dict(st["pruner"])
        opt.load_state_dict(st["opt"])
        sched.load_state_dict(st["sched"])
        epoch, history, best, best_state = st["epoch"], st["history"], st["best"], st["best_state"]
        print(f"resumed after epoch {epoch}")
    if epoch == 0 and (args.init_schedule is not None or args.prior is not None):
        row = {"epoch": 0}
        if args.init_schedule is not None:
            grid = tts.plans.from_tensor(json.loads(args.init_schedule.read_text())["grid"]).decisions[0]
            windows = torch.as_tensor(np.concatenate([e["obs"] for e in train]))
            with torch.no_grad():
                cond = policy.obs_normalizer.normalize(windows)[:, -policy.cfg.n_obs_steps:]
                memory = policy.model.condition_memory(policy.scheduler.timesteps, cond)
            row["init_schedule_agreement"] = distill_schedule(pruner, memory, grid, batch=16, seed=args.seed)
        v = validate(policy, pruner, val, directions, args)
        row.update({f"val_{k}": _mean(v, k) for k in ("l1", "sparsity")})
        row["val_score"] = row["val_l1"] + args.lam * abs(row["val_sparsity"] - args.sparsity)
        print(" ".join(f"{k}={v:.4g}" for k, v in row.items()))
        history.append(row)
        best, best_state = row, {k: v.clone() for k, v in pruner.state_dict().items()}
    rng = np.random.default_rng(args.seed + epoch)
    noise_rng = torch.Generator().manual_seed(args.seed + 1000 * epoch)
    t_start, train_seconds = time.time(), (history[-1].get("train_seconds", 0.0) if history else 0.0)
    for epoch in range(epoch, args.epochs):
        pruner.train()
        acc = tts.accelerate(policy, directions, plan=train_plan, forecast=args.forecast)
        stats = []
        for group in tqdm(episode_groups(train, args.batch, rng), desc=f"epoch {epoch + 1}/{args.epochs}",
                          total=groups_per_epoch):
            stats.append(run_group(policy, train_plan, group, args, noise_rng, opt))
        acc.remove()
        lr = opt.param_groups[0]["lr"]
        sched.step()
        v = validate(policy, pruner, val, directions, args)
        row = {"epoch": epoch + 1, **{f"train_{k}": _mean(stats, k) for k in ("l1", "sparsity")},
               **{f"val_{k}": _mean(v, k) for k in ("l1", "sparsity")}, "lr": lr}
        row["val_score"] = row["val_l1"] + args.lam * abs(row["val_sparsity"] - args.sparsity)
        train_seconds += time.time() - t_start
        t_start = time.time()
        row["train_seconds"] = train_seconds
        history.append(row)
        print(" ".join(f"{k}={v:.4g}" for k, v in row.items()))
        if best is None or row["val_score"] < best["val_score"]:
            best, best_state = row, {k: v.clone() for k, v in pruner.state_dict().items()}
        with atomic_path(state_path) as tmp:
            torch.save({"pruner": pruner.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "epoch": epoch + 1, "history": history, "best": best, "best_state": best_state}, tmp)
        # the best epoch's weights, with the history so far: a usable checkpoint after every epoch
        meta = provenance(seeds={"train": args.seed})
        meta.update(vars_as_json(args), trajectories=str(args.trajectories), n_train_episodes=len(train),
                    n_val_episodes=len(val), policy=str(args.checkpoint), best_epoch=best, history=history,
                    train_seconds=train_seconds,
                    pruner_macs_per_call=pruner.macs(policy.cfg.num_inference_steps, 1 + policy.cfg.n_obs_steps),
                    trajectory_collection=traj_meta.get("command"))
        current = {k: v.clone() for k, v in pruner.state_dict().items()}
        pruner.load_state_dict(best_state)
        save_pruner(pruner, args.out, metadata=meta)
        pruner.load_state_dict(current)
    print(f"best epoch {best['epoch']}: val L1 {best['val_l1']:.4f}, val sparsity {best['val_sparsity']:.3f}; "
          f"wrote {args.out}.safetensors/.json")


def validate(policy, pruner, val, directions, args) -> list[dict]:
    """The test-time rule (``--val-mode``) on the validation episodes, paired or fixed noise."""
    plan = RecordingPlan(pruner, args.val_mode, args.sparsity)
    with tts.accelerate(policy, directions, plan=plan, forecast=args.forecast):
        return [run_group(policy, plan, g, args, torch.Generator().manual_seed(args.seed + 7), None)
                for g in episode_groups(val, args.batch, None)]


class RecordingPlan(PrunerPlan):
    """Test-time decisions (sequential), keeping the last call's codes for the sparsity statistics."""

    def __init__(self, pruner, mode: str = "argmax", sparsity: float | None = None):
        super().__init__(pruner, mode=mode, sparsity=sparsity if mode == "budget" else None, parallel=False)

    def _decide(self, memory) -> None:
        super()._decide(memory)
        self.last_codes = self._result


def _mean(rows: list[dict], key: str) -> float:
    n = sum(r["frames"] for r in rows)
    return sum(r[key] * r["frames"] for r in rows) / max(n, 1)


def vars_as_json(args) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}


if __name__ == "__main__":
    main()
