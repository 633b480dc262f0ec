"""Recorded dense-policy trajectories: the file format, and episode batches in lockstep.

An *episode* is a dict of per-call arrays with a common leading length R (``obs`` [R, To, obs_dim]:
the observation window fed to ``predict_action``; ``action_pred`` [R, H, Da]: the dense action, the
training target; ``noise_seed`` [R]: the seed of that call's noise; for an image policy, its camera
windows under their observation keys, e.g. ``agentview_image`` [R, To, H, W, 3] uint8; plus ``seed``
and ``success``).
:func:`save_trajectories` / :func:`load_trajectories` read and write a file of them.

:func:`episode_groups` shuffles episodes into groups of ``batch`` and :func:`lockstep_frames` walks a
group frame by frame, so that the rollout cache carries from frame r-1 to frame r. Shorter episodes
are padded by repeating their last frame with loss weight 0 (rather than truncating every episode to
the shortest one), so no frame is dropped.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional, Sequence

import numpy as np
import torch

from .io import atomic_path

__all__ = ["Frame", "REPLAY_KEYS", "TRAJECTORY_FORMAT", "Windows", "camera_keys", "episode_groups", "held_out_episodes",
           "load_trajectories", "lockstep_frames", "obs_dict", "replay_keys", "save_trajectories", "split_episodes"]

TRAJECTORY_FORMAT = "tts-trajectories-v1"
REPLAY_KEYS = ("obs", "action_pred", "noise_seed")  # the per-call arrays a replay or the trainer needs


@dataclass
class Frame:
    """One policy call of an episode group in lockstep (:func:`lockstep_frames`)."""

    index: int  # r: frame (policy call) index within the episodes
    data: dict[str, torch.Tensor]  # each [E, ...]
    weight: torch.Tensor  # [E]: 1 for real frames, 0 for padding after an episode ended
    first: bool  # frame 0: the dense call that fills the rollout cache (excluded from the loss)


# -------------------------------------------------------------------- trajectory files
def save_trajectories(path: Path, episodes: list[dict], meta: dict) -> None:
    """Write ``episodes`` and the collection metadata ``meta`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        torch.save({"format": TRAJECTORY_FORMAT, "meta": meta, "episodes": episodes}, tmp)


def load_trajectories(path: Path, successful_only: bool = True) -> tuple[list[dict], dict]:
    """Episodes (dicts of numpy arrays + seed/success) and the collection metadata."""
    doc = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(doc, dict) or doc.get("format") != TRAJECTORY_FORMAT:
        raise ValueError(f"{path} is not a tts trajectory file")
    eps = [e for e in doc["episodes"] if e["success"] or not successful_only]
    return eps, doc["meta"]


def held_out_episodes(path: Path, first: int, successful_only: bool = True) -> tuple[list[dict], int]:
    """The successful (or, with ``successful_only=False``, all) episodes of ``path`` from index ``first``
    on (those a pruner or schedule was not fitted on) and the number of such episodes in all; an error
    if there are none."""
    episodes, _ = load_trajectories(path, successful_only=successful_only)
    if not episodes[first:]:
        raise ValueError(f"no held-out episodes: {len(episodes)} recorded, the first held-out index is {first}")
    return episodes[first:], len(episodes)


def camera_keys(policy: Any) -> tuple[str, ...]:
    """The camera observation keys of an image policy (``image_cfg.cameras``); () for a low-dim one."""
    image_cfg = getattr(policy, "image_cfg", None)
    return tuple(image_cfg.cameras) if image_cfg is not None else ()


def replay_keys(policy: Any) -> tuple[str, ...]:
    """The per-call arrays a replay of ``policy`` needs: :data:`REPLAY_KEYS` and its camera windows."""
    return REPLAY_KEYS + camera_keys(policy)


def obs_dict(policy: Any, window: torch.Tensor, frames: Optional[Mapping[str, Any]] = None) -> dict[str, np.ndarray]:
    """Split a stored obs window [E, To, obs_dim] back into the policy's observation keys
    (``policy.cfg.obs_keys`` / ``obs_dims``, in that order); an image policy's camera windows
    [E, To, H, W, 3] come from ``frames`` (e.g. a :class:`Frame`'s data)."""
    out, i = {}, 0
    for k, d in zip(policy.cfg.obs_keys, policy.cfg.obs_dims):
        out[k] = window[..., i:i + d].numpy()
        i += d
    for k in camera_keys(policy):
        if frames is None or k not in frames:
            raise KeyError(f"the observations given have no {k!r} frames, which this image policy reads (its "
                           "recorded trajectories carry them; tools that read low-dim windows only cannot run it)")
        out[k] = np.asarray(frames[k])
    return out


class Windows:
    """Every call of ``episodes`` as one array per recorded key, for tools that pick calls out of
    order (schedule search, headroom): ``obs(idx)`` -> the policy's observation dict for those calls
    (camera windows included for an image policy)."""

    def __init__(self, policy, episodes: Sequence[dict]):
        self.policy = policy
        self.windows = np.concatenate([e["obs"] for e in episodes])
        self.frames = {k: np.concatenate([e[k] for e in episodes]) for k in camera_keys(policy)
                       if all(k in e for e in episodes)}

    def __len__(self) -> int:
        return len(self.windows)

    def obs(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """The policy's observation dict for the calls ``idx``."""
        return obs_dict(self.policy, torch.as_tensor(self.windows[idx]), {k: v[idx] for k, v in self.frames.items()})


# -------------------------------------------------------------------- lockstep batches
def split_episodes(episodes: Sequence[dict], n_train: int, n_val: int) -> tuple[list[dict], list[dict]]:
    """First ``n_train`` episodes for training, the next ``n_val`` for validation (clear error if short)."""
    if n_train < 1:
        raise ValueError("need at least one training trajectory")
    if len(episodes) < n_train + n_val:
        raise ValueError(
            f"only {len(episodes)} usable trajectories (the successful ones, or every one with --all-episodes); "
            f"asked for {n_train} train + {n_val} val (collect more with eval/collect_trajectories.py --episodes N)"
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
