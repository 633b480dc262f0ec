"""The three reuse caches (spec §2), in one place.

- forward  F[kind]: output of the most recently computed branch of that kind, in execution order
  (layer-major within a step, then step-major); cleared at the start of every sampling call.
- timestep T[b]:    output of branch b at the most recent step of this call where it was computed;
  cleared at the start of every sampling call.
- rollout  R[k][b]: output of branch b at step index k in the most recent earlier call of the
  episode where (k, b) was computed; persists across calls, cleared by :meth:`new_episode`.

Caches hold the branch output *before* the residual add, for the whole batch, and are updated only
on compute. Writes store references (no copy) when every sample computed, and out-of-place
``index_copy`` when only some samples did, so a tensor shared by several slots is never mutated.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from .plans import FORWARD, ROLLOUT, TIMESTEP

__all__ = ["ReuseCache"]


class ReuseCache:
    def __init__(self, kind_of_branch: Sequence[int], num_kinds: int, directions: Sequence[str]):
        self.kind_of_branch = list(kind_of_branch)
        self.num_branches = len(self.kind_of_branch)
        self.num_kinds = num_kinds
        self.use_forward = "forward" in directions
        self.use_timestep = "timestep" in directions
        self.use_rollout = "rollout" in directions
        self.forward: list[Optional[torch.Tensor]] = [None] * num_kinds
        self.timestep: list[Optional[torch.Tensor]] = [None] * self.num_branches
        self.rollout: list[list[Optional[torch.Tensor]]] = []

    # -- lifecycle -------------------------------------------------------------------------------
    def begin_call(self) -> None:
        """Forward and timestep caches live for one sampling call."""
        self.forward = [None] * self.num_kinds
        self.timestep = [None] * self.num_branches

    def new_episode(self) -> None:
        """Rollout caches live for one episode."""
        self.rollout = []

    def rollout_ready(self, k: int) -> bool:
        """True when every branch has a rollout entry for step ``k``."""
        return k < len(self.rollout) and all(t is not None for t in self.rollout[k])

    # -- reads -----------------------------------------------------------------------------------
    def read(self, code: int, b: int, k: int) -> Optional[torch.Tensor]:
        if code == FORWARD:
            return self.forward[self.kind_of_branch[b]]
        if code == TIMESTEP:
            return self.timestep[b]
        if code == ROLLOUT:
            return self.rollout[k][b] if k < len(self.rollout) else None
        raise ValueError(f"not a reuse code: {code}")

    # -- writes (compute only) -------------------------------------------------------------------
    def _rollout_row(self, k: int) -> list[Optional[torch.Tensor]]:
        while len(self.rollout) <= k:
            self.rollout.append([None] * self.num_branches)
        return self.rollout[k]

    def write(self, b: int, k: int, d: torch.Tensor) -> None:
        """Branch b computed for every sample at step k."""
        if self.use_forward:
            self.forward[self.kind_of_branch[b]] = d
        if self.use_timestep:
            self.timestep[b] = d
        if self.use_rollout:
            self._rollout_row(k)[b] = d

    def write_rows(self, b: int, k: int, rows: torch.Tensor, d_rows: torch.Tensor, dim: int) -> None:
        """Branch b computed only for ``rows`` (indices along the batch dim ``dim``) at step k."""

        def merged(old: Optional[torch.Tensor]) -> torch.Tensor:
            if old is None:
                raise RuntimeError(
                    "internal: partial cache write into an empty slot (step 0 and the first call "
                    "of an episode are always computed, so this should not happen)"
                )
            return old.index_copy(dim, rows, d_rows)

        if self.use_forward:
            kind = self.kind_of_branch[b]
            self.forward[kind] = merged(self.forward[kind])
        if self.use_timestep:
            self.timestep[b] = merged(self.timestep[b])
        if self.use_rollout:
            # A slot the previous call never filled (it ran fewer steps) stays empty: a partial
            # entry would be wrong for the other samples; the next call then computes (k, b).
            row = self._rollout_row(k)
            if row[b] is not None:
                row[b] = row[b].index_copy(dim, rows, d_rows)
