"""Training a pruner for a Diffusion-Policy-style policy from recorded dense trajectories.

    episodes, _ = tts.trajectories.load_trajectories("data/trajectories/lift.pt")
    config = PolicyPrunerTrainingConfig(out="checkpoints/pruners/lift", sparsity=0.93, n_train=96, n_val=16,
                                        epochs=4, lr=2e-3, paired=True)
    pruner = train_policy_pruner(policy, episodes, config)

Episode groups of ``config.batch`` run in lockstep, one optimizer step per policy call (frame), so
the rollout cache carries across calls as it does in a rollout. Frame 0 is the dense call that fills
the rollout cache and is excluded from the loss; every later frame runs the full K-step sampler with
straight-through gates (all branches computed and mixed, gradients into the pruner only; the policy
is frozen) and minimises L1(sparse action_pred, dense action_pred) + ``lam`` * |reuse fraction -
sparsity| per sample. ``paired`` replays each frame's recorded noise seed, so the sparse sample is
compared with the same draw the dense policy made; the default, like the paper, uses fresh noise.
Validation uses the test-time rule (``val_mode``); loop, checkpoint and resume: :func:`tts.training.fit`.

The policy is the bundled one (:mod:`tts.adapters.dp_policy`) or anything with its interface:
``predict_action(obs, generator=[...], enable_grad=...)["action_pred"]``, ``reset()``, ``cfg``
(``obs_keys``, ``obs_dims``, ``num_inference_steps``, ``n_obs_steps``), ``model.config`` (``n_emb``,
``n_layer``), ``model.condition_memory``, ``obs_normalizer``, ``action_normalizer`` and
``scheduler.timesteps``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import numpy as np
import torch
from tqdm import tqdm

from .plans import DIRECTIONS, check_directions
from .pruner import PrunerConfig, PrunerModule, PrunerPlan, build_pruner, distill_schedule, pruner_loss
from .trajectories import episode_groups, lockstep_frames, obs_dict, replay_keys, split_episodes
from .training import GridSource, PrunerTrainingConfig, RecordingPlan, fit, mean_of, read_grid

__all__ = ["PolicyPrunerTrainingConfig", "build_policy_pruner", "train_policy_pruner"]


@dataclass
class PolicyPrunerTrainingConfig(PrunerTrainingConfig):
    """:class:`tts.training.PrunerTrainingConfig` plus the options of the policy trainer."""

    paired: bool = False  # replay the dense call's noise (paired target)
    loss_space: str = "raw"  # L1 on raw actions (the paper) or on the policy's normalised actions
    # train a static router instead (Learning-to-Cache-style baseline: one decision per step x branch,
    # not per observation)
    static: bool = False
    # initial head bias per option, compute first, e.g. 2,0,1,0 for (C, F, T, R): when the sparsity
    # term pushes compute down, the preferred direction takes over first
    head_bias: Optional[Union[str, Sequence[float]]] = None
    # warm start: fit the pruner to a searched static schedule by cross-entropy before the
    # straight-through training
    init_schedule: Optional[GridSource] = None

    @classmethod
    def reference(cls, out: Union[str, Path], **overrides: Any) -> "PolicyPrunerTrainingConfig":
        """The reference implementation's recipe: pruner hidden 512, 8 heads, FF 1024, head bias
        zero (argmax starts near uniform over the options, not from a prior), AdamW lr 1e-4 and weight
        decay 1e-4, warm-up then linear decay, no gradient clipping, batches of 16 episodes, 20 epochs,
        unpaired noise. ``overrides`` replace any of these."""
        recipe = dict(hidden=512, heads=8, ffn=1024, lr=1e-4, weight_decay=1e-4, lr_schedule="linear",
                      clip_grad=None, batch=16, epochs=20, paired=False)
        recipe.update(overrides)
        if "head_bias" not in recipe:
            directions = recipe.get("directions", cls.directions)
            n = len(check_directions(directions.split(",") if isinstance(directions, str) else directions))
            recipe["head_bias"] = [0.0] * (1 + n)
        return cls(out=out, **recipe)

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.head_bias, str):
            self.head_bias = [float(x) for x in self.head_bias.split(",")]
        elif self.head_bias is not None:
            self.head_bias = [float(x) for x in self.head_bias]
        if self.loss_space not in ("raw", "normalized"):
            raise ValueError(f"loss_space must be 'raw' or 'normalized', got {self.loss_space!r}")
        if self.static and (self.prior is not None or self.init_schedule is not None or self.head_bias is not None):
            raise ValueError("static trains a table of logits: prior / init_schedule / head_bias do not apply")


def build_policy_pruner(policy: Any, config: PolicyPrunerTrainingConfig) -> PrunerModule:
    """A fresh pruner (or static router) for ``policy``'s branches and steps, with ``config.prior``
    set. Draws its initial weights from torch's global generator."""
    cfg = policy.model.config
    steps = policy.cfg.num_inference_steps
    pruner = build_pruner(PrunerConfig(
        memory_dim=cfg.n_emb, num_branches=3 * cfg.n_layer, directions=config.directions, hidden=config.hidden,
        heads=config.heads, ffn=config.ffn,
        kind="static" if config.static else "transformer", steps=steps, prior=config.prior is not None,
        tie_branches=config.tie_branches, step_query=config.step_query, head_bias=config.head_bias))
    if config.prior is not None:
        pruner.set_prior(read_grid(config.prior, steps, 3 * cfg.n_layer, reuse=config.prior_reuse),
                         margin=config.prior_margin)
    return pruner


def _generators(frame, paired: bool, rng: torch.Generator) -> list[torch.Generator]:
    seeds = (frame.data["noise_seed"].tolist() if paired
             else torch.randint(0, 2**62, (len(frame.weight),), generator=rng).tolist())
    return [torch.Generator().manual_seed(int(s)) for s in seeds]


def _run_group(policy, plan: Optional[PrunerPlan], group, config: PolicyPrunerTrainingConfig, rng: torch.Generator,
               opt=None) -> dict[str, float]:
    """One episode group in lockstep; trains when ``opt`` is given. Returns weighted means. ``plan``
    None: the policy runs untouched (every branch computed, sparsity 0)."""
    policy.reset()
    normalized = config.loss_space == "normalized"  # every action dim on the same [-1, 1] scale
    sums = {"l1": 0.0, "sparsity": 0.0, "n": 0.0}
    mix = {d: 0.0 for d in config.directions} if opt is None else {}  # validation: decisions per direction
    for frame in lockstep_frames(group, replay_keys(policy)):
        obs = obs_dict(policy, frame.data["obs"], frame.data)
        gen = _generators(frame, config.paired, rng)  # CPU generators: the same noise on every device
        target = frame.data["action_pred"].float().to(policy.device)
        if normalized:
            target = policy.action_normalizer.normalize(target)
        if frame.first:
            policy.predict_action(obs, generator=gen)  # dense: fills the rollout cache
            continue
        w = frame.weight.to(policy.device)
        pred = policy.predict_action(obs, generator=gen, enable_grad=opt is not None)["action_pred"]
        if normalized:
            pred = policy.action_normalizer.normalize(pred)
        if opt is not None:
            out = pruner_loss(pred, target, plan.gates, config.sparsity, config.lam, w)
            opt.zero_grad(set_to_none=True)
            out["loss"].backward()
            if config.clip_grad is not None:
                torch.nn.utils.clip_grad_norm_(plan.pruner.parameters(), config.clip_grad)
            opt.step()
            l1 = float(out["l1"].detach())
            reuse = out["reuse"].detach()
        else:
            l1 = float(((pred - target).abs().reshape(len(w), -1).mean(1) * w).sum() / w.sum().clamp_min(1))
            reuse = (torch.zeros_like(w) if plan is None
                     else (plan.last_codes != 0).float().mean((1, 2)).to(w.device))
            for d in mix if plan is not None else ():
                share = (plan.last_codes == DIRECTIONS[d]).float().mean((1, 2)).to(w.device)
                mix[d] += float((share * w).sum())
        n = float(w.sum())
        sums["l1"] += l1 * n
        sums["sparsity"] += float((reuse * w).sum())
        sums["n"] += n
    n = max(sums["n"], 1.0)
    return {"l1": sums["l1"] / n, "sparsity": sums["sparsity"] / n, **{f"reuse_{d}": x / n for d, x in mix.items()},
            "frames": sums["n"]}


def _validation_rows(policy, plan: Optional[PrunerPlan], val: Sequence[dict],
                     config: PolicyPrunerTrainingConfig) -> list[dict]:
    """One validation pass over ``val`` under ``plan`` (None: the untouched policy), every group with
    the same noise generator, so that passes of different plans draw the same noise."""
    return [_run_group(policy, plan, g, config, torch.Generator().manual_seed(config.seed + 7), None)
            for g in episode_groups(val, config.batch, None)]


def train_policy_pruner(policy: Any, episodes: Sequence[dict], config: PolicyPrunerTrainingConfig, *,
                        pruner: Optional[PrunerModule] = None, metadata: Optional[Mapping[str, Any]] = None,
                        log: Optional[Callable[[str], None]] = print) -> PrunerModule:
    """Train a pruner for ``policy`` on recorded ``episodes`` (the first ``n_train`` for training,
    the next ``n_val`` for validation; see :func:`tts.trajectories.load_trajectories`) on the
    policy's device (the pruner must be on the same one). Writes
    ``<config.out>.safetensors/.json`` and returns the best epoch's pruner, its checkpoint metadata in
    ``.metadata``. ``pruner``: train this one instead of :func:`build_policy_pruner`'s (which is
    seeded with ``config.seed``). ``metadata``: extra checkpoint metadata (e.g. provenance)."""
    from . import accelerate

    train, val = split_episodes(episodes, config.n_train, config.n_val)
    policy.requires_grad_(False)
    if pruner is None:
        torch.manual_seed(config.seed)
        pruner = build_policy_pruner(policy, config)
    directions = config.directions
    train_plan = PrunerPlan(pruner, mode="ste", sparsity=config.sparsity if config.train_budget else None,
                            autocast=config.autocast)

    def train_epoch(opt, rng, noise_rng, epoch, progress):
        groups = list(episode_groups(train, config.batch, rng))
        rows = list(progress.rows)  # the groups an interrupted run already trained
        with accelerate(policy, directions, plan=train_plan, forecast=config.forecast):
            for group in tqdm(groups[progress.skip:], desc=f"epoch {epoch + 1}/{config.epochs}",
                              initial=progress.skip, total=len(groups), disable=log is None):
                rows.append(_run_group(policy, train_plan, group, config, noise_rng, opt))
                progress.done(rows)  # resumable from here
        return rows

    def validate():
        plan = RecordingPlan(pruner, config.val_mode, config.sparsity)
        with accelerate(policy, directions, plan=plan, forecast=config.forecast):
            return _validation_rows(policy, plan, val, config)

    def warm_start():
        windows = torch.as_tensor(np.concatenate([e["obs"] for e in train])).to(policy.device)
        with torch.no_grad():
            cond = policy.obs_normalizer.normalize(windows)[:, -policy.cfg.n_obs_steps:]
            memory = policy.model.condition_memory(policy.scheduler.timesteps, cond)
        grid = read_grid(config.init_schedule)
        return {"init_schedule_agreement": distill_schedule(pruner, memory, grid, batch=16, seed=config.seed)}

    meta = dict(metadata or {}, n_train_episodes=len(train), n_val_episodes=len(val))
    if val:  # the untouched policy's val L1 (same noise draws): what another noise draw alone costs
        meta["val_l1_dense"] = mean_of(_validation_rows(policy, None, val, config), "l1")
    fit(pruner, config, train_epoch=train_epoch, validate=validate, steps=policy.cfg.num_inference_steps,
        memory_tokens=1 + policy.cfg.n_obs_steps, metadata=meta,
        warm_start=warm_start if config.init_schedule is not None else None, log=log)
    return pruner.eval()
