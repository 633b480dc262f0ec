"""Replaying recorded dense-policy episodes through a (possibly accelerated) policy."""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import torch

from tts.trajectories import Frame, lockstep_frames, obs_dict, replay_keys

__all__ = ["replay"]


def replay(policy, episodes: Sequence[dict], fn: Optional[Callable[[Frame], None]] = None) -> None:
    """Run ``policy`` over recorded episodes in lockstep with their recorded noise; ``fn(frame)``
    after each call."""
    policy.reset()
    for frame in lockstep_frames(episodes, replay_keys(policy)):
        gen = [torch.Generator().manual_seed(int(s)) for s in frame.data["noise_seed"].tolist()]
        policy.predict_action(obs_dict(policy, frame.data["obs"], frame.data), generator=gen)
        if fn is not None:
            fn(frame)
