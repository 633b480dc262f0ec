"""Replaying recorded dense-policy episodes through a (possibly accelerated) policy."""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import torch

from tts.trajectories import Frame, lockstep_frames, obs_dict, replay_keys

__all__ = ["replay"]


def replay(policy, episodes: Sequence[dict], fn: Optional[Callable[[Frame, dict], None]] = None, *,
           noise_offset: int = 0) -> None:
    """Run ``policy`` over recorded episodes in lockstep with their recorded noise (each call's seed
    plus ``noise_offset``: 0 replays the recorded draw, anything else another one); ``fn(frame, out)``
    after each call, ``out`` being what ``predict_action`` returned."""
    policy.reset()
    for frame in lockstep_frames(episodes, replay_keys(policy)):
        gen = [torch.Generator().manual_seed(int(s) + noise_offset) for s in frame.data["noise_seed"].tolist()]
        out = policy.predict_action(obs_dict(policy, frame.data["obs"], frame.data), generator=gen)
        if fn is not None:
            fn(frame, out)
