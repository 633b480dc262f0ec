"""Timing policy calls on recorded observation windows (eval/latency.py, eval/frontier_latency.py)."""
from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch

from tts.trajectories import camera_keys, obs_dict

__all__ = ["time_calls", "batch_frames", "computed_steps", "timed_image_encoder"]


def _sync(policy) -> None:
    if policy.device.type == "cuda":
        torch.cuda.synchronize(policy.device)


def time_calls(policy, frames: list[dict], gen_seed: int) -> list[float]:
    """reset, untimed frame 0, then the latency of each later frame."""
    policy.reset()
    out = []
    for r, obs in enumerate(frames):
        g = torch.Generator().manual_seed(gen_seed + r)
        _sync(policy)
        t0 = time.perf_counter()
        policy.predict_action(obs, generator=g)
        _sync(policy)
        if r:
            out.append(time.perf_counter() - t0)
    return out


def batch_frames(policy, episodes: list[dict], n_frames: int) -> list[dict]:
    """Frames 0..n_frames of a batch of episodes (an episode shorter than that repeats its last frame)."""
    frames = []
    for r in range(n_frames + 1):
        at = [min(r, len(e["obs"]) - 1) for e in episodes]
        window = torch.as_tensor(np.stack([e["obs"][i] for e, i in zip(episodes, at)]))
        cams = {k: np.stack([e[k][i] for e, i in zip(episodes, at)]) for k in camera_keys(policy)}
        frames.append(obs_dict(policy, window, cams))
    return frames


def computed_steps(summary) -> int:
    """Steps per sample that compute at least one branch, in the last call that was not an episode's
    dense first call (rounded mean over the batch)."""
    call = [c for c in summary.calls if not c.dense][-1]
    d = call.decisions()  # [K, B, nb]
    return int(round(float((d == 0).any(-1).float().sum(0).mean())))


@contextmanager
def timed_image_encoder(policy) -> Iterator[list[float]]:
    """Seconds of every call of the policy's image encoder (``obs_encoder``) inside the block, for the
    encoder's share of an untouched policy's call; an empty list for a policy without one."""
    times: list[float] = []
    encoder = getattr(policy, "obs_encoder", None)
    if not isinstance(encoder, torch.nn.Module):
        yield times
        return
    own = encoder.__dict__.get("forward")  # an instance-level forward (another timer) is put back
    inner = encoder.forward

    def forward(*args, **kwargs):
        _sync(policy)
        t0 = time.perf_counter()
        out = inner(*args, **kwargs)
        _sync(policy)
        times.append(time.perf_counter() - t0)
        return out

    encoder.forward = forward
    try:
        yield times
    finally:
        if own is None:
            del encoder.forward
        else:
            encoder.forward = own
