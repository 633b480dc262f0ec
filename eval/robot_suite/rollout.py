"""Batched rollouts of a policy in robosuite: one episode per environment, observations stacked into
one policy call per step of the action chunk (batch = number of environments)."""
from __future__ import annotations

import collections
import time
from typing import Optional

import numpy as np
import torch

from tts.trajectories import camera_keys

from .tasks import TASKS, camera_obs, low_dim_obs, make_env, reset_env, step_unobserved

__all__ = ["noise_seed", "run_wave", "policy_cameras", "make_policy_envs"]


def policy_cameras(policy) -> list[str]:
    """The cameras an image policy reads (``agentview`` for its ``agentview_image`` key); [] for a
    low-dim policy."""
    return [k.removesuffix("_image") for k in camera_keys(policy)]


def make_policy_envs(policy, task: str, n: int) -> list:
    """``n`` envs of ``task`` that render what ``policy`` observes (its cameras, at its image size)."""
    cams = policy_cameras(policy)
    size = policy.image_cfg.image_size if cams else 84
    return [make_env(task, cameras=cams, image_size=size) for _ in range(n)]


def noise_seed(episode_seed: int, call: int) -> int:
    """Seed of the sampling noise of one policy call of one episode (recorded trajectories)."""
    return episode_seed * 1000 + call


def run_wave(policy, envs, seeds, task, generator, record: bool = False,
             horizon: Optional[int] = None, full_horizon: bool = False) -> tuple[list[dict], list[float]]:
    """Run one episode per env in lockstep; returns per-episode outcomes and per-call latencies.

    ``record=True``: every env gets its own noise generator per call (seeded by :func:`noise_seed`,
    so a sample's noise does not depend on the batch) and each outcome carries its trajectory: the
    obs window fed to the policy [R, To, obs_dim], the dense ``action_pred`` [R, H, Da], the
    executed chunk [R, Ta, Da] and the noise seeds [R] (R = calls until success or the horizon).
    An image policy's camera windows [R, To, H, W, 3] are recorded under their observation keys.
    ``full_horizon=True``: every episode runs to the horizon, also after success (the policy keeps
    acting; ``success`` says whether the task was ever solved), and its frames after success are
    recorded too, as the reference's pruner training data includes them.
    """
    cfg = policy.cfg
    n = len(seeds)
    cams, cam_keys = policy_cameras(policy), list(camera_keys(policy))
    keys = [*cfg.obs_keys, *cam_keys] if cams else TASKS[task].obs_keys

    def observe(raw: dict) -> dict:
        return {**low_dim_obs(raw), **camera_obs(raw, cams)} if cams else low_dim_obs(raw)

    policy.reset()
    raws = [reset_env(env, s) for env, s in zip(envs[:n], seeds)]
    hist = [collections.deque([observe(r)] * cfg.n_obs_steps, maxlen=cfg.n_obs_steps) for r in raws]
    success = [False] * n
    steps = [0] * n
    coverage = [0.0] * n  # Push-T: the best goal coverage reached (Diffusion Policy's score for the task)
    traj = [{"obs": [], "action_pred": [], "action": [], "noise_seed": [], **{k: [] for k in cam_keys}}
            for _ in range(n)]
    latencies = []
    horizon = horizon or TASKS[task].horizon
    t = 0
    call = 0
    def done(e: int) -> bool:  # an env that stops acting: solved, unless the episode runs to the horizon
        return success[e] and not full_horizon

    while t < horizon and not all(done(e) for e in range(n)):
        obs = {k: np.stack([np.stack([h[j][k] for j in range(cfg.n_obs_steps)]) for h in hist]) for k in keys}
        gen = [torch.Generator().manual_seed(noise_seed(s, call)) for s in seeds] if record else generator
        t0 = time.perf_counter()
        out = policy.predict_action(obs, generator=gen)
        latencies.append(time.perf_counter() - t0)
        actions = out["action"].cpu().numpy()
        if record:
            window = policy.obs_vector(obs).cpu().numpy()
            for e in range(n):
                if not done(e):
                    for key, val in (("obs", window[e]), ("action_pred", out["action_pred"][e].cpu().numpy()),
                                     ("action", actions[e]), ("noise_seed", noise_seed(seeds[e], call)),
                                     *((k, obs[k][e]) for k in cam_keys)):
                        traj[e][key].append(val)
        for a_i in range(actions.shape[1]):
            # only the last n_obs_steps observations of a chunk reach the next call: camera envs skip
            # rendering the others (the frames that are read stay exact)
            read = not cams or a_i >= actions.shape[1] - cfg.n_obs_steps
            for e in range(n):
                if done(e):
                    continue  # finished envs keep their last observation (batch size stays constant)
                if read:
                    raw, _, _, _ = envs[e].step(actions[e, a_i])
                    hist[e].append(observe(raw))
                else:
                    step_unobserved(envs[e], actions[e, a_i])
                steps[e] += 1
                coverage[e] = max(coverage[e], float(getattr(envs[e], "coverage", 0.0)))
                if envs[e]._check_success():
                    success[e] = True
            t += 1
            if t >= horizon or all(done(e) for e in range(n)):
                break
        call += 1
    outcomes = [{"seed": s, "success": bool(ok), "env_steps": st} for s, ok, st in zip(seeds, success, steps)]
    if any(hasattr(env, "coverage") for env in envs[:n]):
        for o, c in zip(outcomes, coverage):
            o["max_coverage"] = c
    if record:
        for o, tr in zip(outcomes, traj):
            o["trajectory"] = {k: np.stack(v) for k, v in tr.items()}
    return outcomes, latencies
