"""Where the sampling loop stands: call boundaries, the step index, episodes and batch sizes.

A *sampling call* is one run of the denoising loop (K forwards of the denoiser); an *episode* is a
sequence of calls of a robot policy whose rollout cache is shared. A call starts either explicitly
(a boundary method such as ``predict_action`` was entered, or :meth:`CallTracker.mark_call`) or,
without boundaries, when the timestep argument stops moving monotonically (down for DDPM/DDIM, up
for some flow samplers). A repeated timestep starts a call too: solvers whose schedule repeats one
need boundaries or explicit calls.
"""
from __future__ import annotations

from typing import Optional

import torch

from .spec import Target

__all__ = ["CallTracker"]


class CallTracker:
    """Step counter and call/episode boundaries of one accelerated model.

    ``k`` is the index of the current denoising step within the current call, ``batch`` the call's
    batch size, and ``dense_call`` whether the call is the first of an episode with the rollout
    direction on (it computes every branch to fill the rollout cache).
    """

    def __init__(self, target: Target, use_rollout: bool):
        self._timestep_of = target.timestep_of
        self._batch_of = target.batch_of
        self.use_rollout = use_rollout
        self.explicit = bool(target.boundaries)  # calls start at mark_call(), not by timestep motion
        self.pending = True  # explicit mode: the next forward starts a call
        self.k = 0
        self.batch: Optional[int] = None
        self.dense_call = False
        self.episode_dense = use_rollout  # the next call is the first of an episode
        self._episode_batch: Optional[int] = None
        self._t0: Optional[float] = None
        self._t_prev = 0.0
        self._tdir = 0.0

    def mark_call(self, explicit: bool = False) -> None:
        """The next denoiser forward is step 0 of a new call; ``explicit`` switches timestep
        detection off for good (the caller marks every call from now on)."""
        if explicit:
            self.explicit = True
        self.pending = True

    def new_episode(self) -> None:
        """Episode boundary: the next call runs dense (rollout direction) and may change batch size."""
        self.episode_dense = self.use_rollout
        self._episode_batch = None

    def begin_step(self, args: tuple, kwargs: dict) -> bool:
        """Called at every denoiser forward; True when it starts a new sampling call (``k`` is then 0).

        Raises ValueError when the batch size changes inside a call, or inside a rollout episode.
        """
        batch = self._batch_of(args, kwargs)
        if self._is_new_call(args, kwargs) or self.batch is None:
            self._start_call(batch)
            return True
        if batch != self.batch:
            raise ValueError(
                f"batch size changed from {self.batch} to {batch} inside a sampling call "
                f"(step {self.k}); call acc.new_call() when starting a new call"
            )
        return False

    def end_step(self) -> None:
        """The current step finished: the next forward is step ``k + 1`` (or a new call)."""
        self.k += 1

    def _start_call(self, batch: int) -> None:
        self.pending = False
        self.k = 0
        if self.use_rollout and not self.episode_dense and batch != self._episode_batch:
            raise ValueError(
                f"batch size changed from {self._episode_batch} to {batch} within a rollout "
                "episode; the rollout cache is per sample. Call acc.new_rollout() (or the "
                "policy's reset()) when the set of environments changes."
            )
        self.dense_call = self.episode_dense
        if self.dense_call:
            self.episode_dense = False
            self._episode_batch = batch
        self.batch = batch

    def _is_new_call(self, args: tuple, kwargs: dict) -> bool:
        if self.explicit:
            return self.pending
        t = self._timestep_of(args, kwargs)
        if t is None:
            raise ValueError(
                "tts cannot tell where a sampling call starts: the denoiser was called without a "
                "timestep argument. Call acc.new_call() before each sampling call."
            )
        t = float(t.reshape(-1)[0]) if isinstance(t, torch.Tensor) else float(t)
        # A step that does not continue the motion of the call's timesteps starts a new call.
        if self._t0 is None or self.k == 0:
            new = True
        elif self.k == 1:
            new = t == self._t0
            self._tdir = 0.0 if new else (1.0 if t > self._t0 else -1.0)
        else:
            new = (t - self._t_prev) * self._tdir <= 0
        if new:
            self._t0 = t
        self._t_prev = t
        return new
