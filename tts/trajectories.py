"""Episode batches in lockstep (spec §4): the rollout cache carries from frame r-1 to frame r.

An *episode* is a dict of per-call arrays with a common leading length R (e.g. ``obs`` [R, To, d],
``action_pred`` [R, H, Da], ``noise_seed`` [R]). :func:`episode_groups` shuffles episodes into groups
of ``batch`` and :func:`lockstep_frames` walks a group frame by frame. Unlike the reference, which
truncates every episode to the shortest one (spec §10 item 4), shorter episodes are padded by
repeating their last frame with loss weight 0, so no frame is dropped.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import torch

__all__ = ["Frame", "episode_groups", "lockstep_frames", "split_episodes"]


@dataclass
class Frame:
    index: int  # r: frame (policy call) index within the episodes
    data: dict[str, torch.Tensor]  # each [E, ...]
    weight: torch.Tensor  # [E]: 1 for real frames, 0 for padding after an episode ended
    first: bool  # frame 0: the dense call that fills the rollout cache (excluded from the loss)


def split_episodes(episodes: Sequence[dict], n_train: int, n_val: int) -> tuple[list[dict], list[dict]]:
    """First ``n_train`` episodes for training, the next ``n_val`` for validation (clear error if short)."""
    if n_train < 1:
        raise ValueError("need at least one training trajectory")
    if len(episodes) < n_train + n_val:
        raise ValueError(
            f"only {len(episodes)} successful trajectories; asked for {n_train} train + {n_val} val "
            "(collect more with eval/collect_trajectories.py --episodes N)"
        )
    return list(episodes[:n_train]), list(episodes[n_train:n_train + n_val])


def episode_groups(episodes: Sequence[dict], batch: int, rng: np.random.Generator | None) -> list[list[dict]]:
    """Shuffle (if ``rng``) and cut into groups of at most ``batch`` episodes."""
    order = np.arange(len(episodes)) if rng is None else rng.permutation(len(episodes))
    return [[episodes[i] for i in order[s:s + batch]] for s in range(0, len(order), batch)]


def lockstep_frames(group: Sequence[dict], keys: Sequence[str]) -> Iterator[Frame]:
    """Frames r = 0 .. max length - 1 of a group, all episodes in lockstep."""
    lengths = [len(ep[keys[0]]) for ep in group]
    for ep, n in zip(group, lengths):
        for k in keys:
            if len(ep[k]) != n:
                raise ValueError(f"episode arrays differ in length: {k} has {len(ep[k])}, {keys[0]} has {n}")
    for r in range(max(lengths)):
        data = {k: torch.as_tensor(np.stack([np.asarray(ep[k][min(r, n - 1)]) for ep, n in zip(group, lengths)]))
                for k in keys}
        weight = torch.tensor([1.0 if r < n else 0.0 for n in lengths])
        yield Frame(index=r, data=data, weight=weight, first=r == 0)
