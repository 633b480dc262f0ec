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
import math
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from collect_trajectories import load_trajectories  # noqa: E402
from common import parse_args  # noqa: E402
from pruner_fit import RecordingPlan, add_training_args, fit, read_grid  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.pruner import PrunerConfig, PrunerPlan, build_pruner, distill_schedule, pruner_loss  # noqa: E402
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
    add_training_args(ap, sparsity=0.93, directions="forward,timestep,rollout", batch=16)
    ap.add_argument("--n-train", type=int, default=32)
    ap.add_argument("--n-val", type=int, default=16)
    ap.add_argument("--paired", action="store_true", help="replay the dense call's noise (paired target)")
    ap.add_argument("--loss-space", choices=["raw", "normalized"], default="raw",
                    help="L1 on raw actions (the paper) or on the policy's normalised actions")
    ap.add_argument("--static", action="store_true",
                    help="train a static router instead (Learning-to-Cache-style baseline: one decision per "
                         "step x branch, not per observation)")
    ap.add_argument("--head-bias", default=None,
                    help="initial head bias per option, compute first, e.g. 2,0,1,0 for (C, F, T, R): when the "
                         "sparsity term pushes compute down, the preferred direction takes over first")
    ap.add_argument("--init-schedule", type=Path, default=None,
                    help="warm start: fit the pruner to a searched static schedule (eval/search_static.py JSON) "
                         "by cross-entropy before the straight-through training")
    args = parse_args(ap, argv)
    tts.plans.check_sparsity(args.sparsity)
    directions = tts.plans.check_directions(args.directions.split(","))
    torch.manual_seed(args.seed)
    if args.static and (args.prior or args.init_schedule or args.head_bias):
        raise SystemExit("--static trains a table of logits: --prior / --init-schedule / --head-bias do not apply")

    episodes, traj_meta = load_trajectories(args.trajectories)
    train, val = split_episodes(episodes, args.n_train, args.n_val)
    policy = load_policy(args.checkpoint).requires_grad_(False)
    cfg = policy.model.config
    K = policy.cfg.num_inference_steps
    pruner = build_pruner(PrunerConfig(
        memory_dim=cfg.n_emb, num_branches=3 * cfg.n_layer, directions=directions, hidden=args.hidden,
        kind="static" if args.static else "transformer", steps=K, prior=args.prior is not None,
        tie_branches=args.tie_branches, step_query=args.step_query,
        head_bias=[float(x) for x in args.head_bias.split(",")] if args.head_bias else None))
    if args.prior is not None:
        pruner.set_prior(read_grid(args.prior, reuse=args.prior_reuse), margin=args.prior_margin)
    train_plan = PrunerPlan(pruner, mode="ste", sparsity=args.sparsity if args.train_budget else None)

    def train_epoch(opt, rng, noise_rng, epoch):
        with tts.accelerate(policy, directions, plan=train_plan, forecast=args.forecast):
            return [run_group(policy, train_plan, group, args, noise_rng, opt)
                    for group in tqdm(episode_groups(train, args.batch, rng), desc=f"epoch {epoch + 1}/{args.epochs}",
                                      total=math.ceil(len(train) / args.batch))]

    def validate():
        plan = RecordingPlan(pruner, args.val_mode, args.sparsity)
        with tts.accelerate(policy, directions, plan=plan, forecast=args.forecast):
            return [run_group(policy, plan, g, args, torch.Generator().manual_seed(args.seed + 7), None)
                    for g in episode_groups(val, args.batch, None)]

    def warm_start():
        windows = torch.as_tensor(np.concatenate([e["obs"] for e in train]))
        with torch.no_grad():
            cond = policy.obs_normalizer.normalize(windows)[:, -policy.cfg.n_obs_steps:]
            memory = policy.model.condition_memory(policy.scheduler.timesteps, cond)
        grid = read_grid(args.init_schedule)
        return {"init_schedule_agreement": distill_schedule(pruner, memory, grid, batch=16, seed=args.seed)}

    fit(pruner, args, train_epoch=train_epoch, validate=validate,
        metadata=lambda: dict(trajectories=str(args.trajectories), n_train_episodes=len(train),
                              n_val_episodes=len(val), policy=str(args.checkpoint),
                              trajectory_collection=traj_meta.get("command")),
        steps=K, memory_tokens=1 + policy.cfg.n_obs_steps,
        warm_start=warm_start if args.init_schedule is not None else None)


if __name__ == "__main__":
    main()
