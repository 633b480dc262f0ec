"""The three reuse caches, in one place.

- forward  F[kind]: output of the most recently computed branch of that kind, in execution order
  (layer-major within a step, then step-major); cleared at the start of every sampling call.
- timestep T[b]:    output of branch b at the most recent step of this call where it was computed;
  cleared at the start of every sampling call.
- rollout  R[k][b]: output of branch b at step index k in the most recent earlier call of the
  episode where (k, b) was computed; persists across calls, cleared by :meth:`new_episode`.

Caches hold the branch output *before* the residual add, for the whole batch, and are updated only
on compute. Writes store references (no copy) when every sample computed, and out-of-place
``index_copy`` when only some samples did, so a tensor shared by several slots is never mutated.

``forecast=O`` (O >= 1) turns timestep reuse into a TaylorSeer-style forecast (Liu et al. 2025,
"From Reusing to Forecasting"): besides the last computed output, each timestep slot keeps O
finite-difference derivatives along the step index (D_{i+1} = (D_i - D_i,previous) / steps between
the two computes), and a reuse at step k returns sum_i D_i (k - k_last)^i / i!. Steps are tracked
per sample, so samples that computed at different steps forecast from their own history.

:meth:`ReuseCache.step_total` serves whole-step fusion (see :mod:`tts.spec`): the sum over branches
of what a step reads. Timestep sums are kept until the next write (``version``); with a forecast
they are kept per Taylor order, so a fused step costs O + 1 tensor ops whatever the depth.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import torch

from .plans import FORWARD, ROLLOUT, TIMESTEP

__all__ = ["ReuseCache", "TaylorSlot"]


Steps = Union[int, torch.Tensor]  # step of the last compute: one int for the whole batch, or [B]


class TaylorSlot:
    """Last computed output of one branch plus up to ``order`` step-derivatives (forecast reuse).

    ``step`` and ``valid`` (how many of ``derivs`` a sample has history for) are ints while every
    sample computed at the same steps, per-sample [B] tensors once they differ."""

    __slots__ = ("derivs", "step", "valid", "dim")

    def __init__(self, d: torch.Tensor, step: Steps, dim: int, valid: Steps = 1):
        self.derivs: list[torch.Tensor] = [d]
        self.step: Steps = step
        self.valid: Steps = valid
        self.dim = dim

    def _rows_shape(self, like: torch.Tensor, n: int) -> list[int]:
        shape = [1] * like.dim()
        shape[self.dim] = n
        return shape

    def _vector(self, x: Steps, n: int, device) -> torch.Tensor:
        return x if torch.is_tensor(x) else torch.full((n,), int(x), dtype=torch.long, device=device)

    def update(self, d: torch.Tensor, step: int, order: int) -> "TaylorSlot":
        """All rows computed ``d`` at ``step``."""
        n = d.shape[self.dim]
        return self.update_rows(torch.arange(n, device=d.device), d, step, order, all_rows=True)

    def update_rows(self, rows: torch.Tensor, d_rows: torch.Tensor, step: int, order: int,
                    all_rows: bool = False) -> "TaylorSlot":
        """``rows`` computed ``d_rows`` at ``step``; the other rows keep their history."""
        old = self.derivs[0]
        rows = rows.to(old.device)
        n = old.shape[self.dim]
        uniform = all_rows and not torch.is_tensor(self.step) and not torch.is_tensor(self.valid)
        if uniform:  # the common case: plain tensors, no per-row bookkeeping
            out = TaylorSlot(d_rows, step, self.dim, min(self.valid + 1, order + 1))
            gap = float(max(step - self.step, 1))  # a branch run twice in one step: no division by 0
            for i in range(min(order, self.valid)):
                out.derivs.append((out.derivs[i] - self.derivs[i]) / gap)
            return out
        last = self._vector(self.step, n, old.device)
        valid = self._vector(self.valid, n, old.device)
        v_rows = valid.index_select(0, rows)
        gap = (step - last.index_select(0, rows)).clamp_min(1).to(old.dtype)
        gap = gap.reshape(self._rows_shape(old, len(rows)))
        out = TaylorSlot(old.index_copy(self.dim, rows, d_rows),
                         last.index_copy(0, rows, torch.full_like(rows, step)), self.dim,
                         valid.index_copy(0, rows, (v_rows + 1).clamp_max(order + 1)))
        new_i = d_rows
        for i in range(min(order, int(valid.max()))):
            known = (v_rows > i).to(old.dtype).reshape(self._rows_shape(old, len(rows)))
            new_next = (new_i - self.derivs[i].index_select(self.dim, rows)) / gap * known
            base = self.derivs[i + 1] if i + 1 < len(self.derivs) else torch.zeros_like(old)
            out.derivs.append(base.index_copy(self.dim, rows, new_next))
            new_i = new_next
        return out

    def forecast(self, step: int) -> torch.Tensor:
        """The slot's value at ``step``: the last output, plus the Taylor terms when derivatives are kept."""
        base = self.derivs[0]
        if len(self.derivs) == 1:
            return base
        if not torch.is_tensor(self.step):
            h = float(step - self.step)
            out = base
            for i, d in enumerate(self.derivs[1:], 1):
                out = torch.add(out, d, alpha=h ** i / math.factorial(i))
            return out
        h = (step - self.step).to(base.dtype).reshape(self._rows_shape(base, base.shape[self.dim]))
        out = base
        for i, d in enumerate(self.derivs[1:], 1):
            out = out + d * (h ** i / math.factorial(i))
        return out


class ReuseCache:
    """The forward, timestep and rollout caches of one accelerated model (semantics: module docstring)."""

    def __init__(self, kind_of_branch: Sequence[int], num_kinds: int, directions: Sequence[str],
                 forecast: int = 0, batch_dims: Optional[Sequence[int]] = None):
        if int(forecast) < 0:
            raise ValueError(f"forecast order must be >= 0, got {forecast}")
        self.forecast = int(forecast)
        self.batch_dims = list(batch_dims) if batch_dims is not None else [0] * len(kind_of_branch)
        self.kind_of_branch = list(kind_of_branch)
        self.num_branches = len(self.kind_of_branch)
        self.num_kinds = num_kinds
        self.use_forward = "forward" in directions
        self.use_timestep = "timestep" in directions
        self.use_rollout = "rollout" in directions
        self.forward: list[Optional[torch.Tensor]] = [None] * num_kinds
        self.timestep: list = [None] * self.num_branches  # tensors, or TaylorSlots when forecasting
        self.rollout: list[list[Optional[torch.Tensor]]] = []
        self.version = 0  # bumped by every write and clear: keys the memo of step_total
        self._sums: Optional[tuple[int, TaylorSlot]] = None  # (version, slots summed over branches)
        # per step k: (version of rollout row k, the row summed over branches), for fused rollout steps
        self._rollout_versions: list[int] = []
        self._rollout_sums: dict[int, tuple[int, torch.Tensor]] = {}

    # -- lifecycle -------------------------------------------------------------------------------
    def begin_call(self) -> None:
        """Forward and timestep caches live for one sampling call."""
        self.forward = [None] * self.num_kinds
        self.timestep = [None] * self.num_branches
        self.version += 1

    def new_episode(self) -> None:
        """Rollout caches live for one episode."""
        self.rollout = []
        self._rollout_versions, self._rollout_sums = [], {}
        self.version += 1

    def rollout_ready(self, k: int) -> bool:
        """True when every branch has a rollout entry for step ``k``."""
        return k < len(self.rollout) and all(t is not None for t in self.rollout[k])

    # -- reads -----------------------------------------------------------------------------------
    def read(self, code: int, b: int, k: int) -> Optional[torch.Tensor]:
        """What branch ``b`` reuses at step ``k`` under decision ``code``; None when that cache is empty."""
        if code == FORWARD:
            return self.forward[self.kind_of_branch[b]]
        if code == TIMESTEP:
            slot = self.timestep[b]
            return slot.forecast(k) if self.forecast and slot is not None else slot
        if code == ROLLOUT:
            return self.rollout[k][b] if k < len(self.rollout) else None
        raise ValueError(f"not a reuse code: {code}")

    def step_total(self, codes: Sequence[int], k: int) -> torch.Tensor:
        """Sum over branches b of ``read(codes[b], b, k)``: what a fused step adds to the stream."""
        if all(c == TIMESTEP for c in codes):
            summed = self._timestep_sum()
            if summed is not None:
                return summed.forecast(k)
        if all(c == ROLLOUT for c in codes) and self.rollout_ready(k):
            return self._rollout_sum(k)
        total = None
        for b, code in enumerate(codes):
            d = self.read(code, b, k)
            if d is None:
                raise RuntimeError(f"internal: empty cache (code {code}) for branch {b} in a fused step")
            total = d if total is None else total + d
        return total

    def _timestep_sum(self) -> Optional[TaylorSlot]:
        """The timestep slots summed over branches, per Taylor order (a forecast is linear in its
        derivatives), or None when they do not share one history (samples or branches computed at
        different steps): then the step is summed branch by branch."""
        if self._sums is not None and self._sums[0] == self.version:
            return self._sums[1]
        slots = self.timestep
        if not self.forecast:
            summed = TaylorSlot(torch.stack(slots).sum(0), 0, 0)
        else:
            first = slots[0]
            if any(torch.is_tensor(s.step) or torch.is_tensor(s.valid) or s.step != first.step
                   or len(s.derivs) != len(first.derivs) for s in slots):
                return None
            summed = TaylorSlot(torch.stack([s.derivs[0] for s in slots]).sum(0), first.step, first.dim)
            summed.derivs += [torch.stack([s.derivs[i] for s in slots]).sum(0) for i in range(1, len(first.derivs))]
        self._sums = (self.version, summed)
        return summed

    def _rollout_sum(self, k: int) -> torch.Tensor:
        """Rollout row ``k`` summed over branches, kept until the row changes: a static plan reuses
        the same row in every call of an episode."""
        version = self._rollout_versions[k]
        memo = self._rollout_sums.get(k)
        if memo is None or memo[0] != version:
            memo = self._rollout_sums[k] = (version, torch.stack(self.rollout[k]).sum(0))
        return memo[1]

    # -- writes (compute only) -------------------------------------------------------------------
    def _rollout_row(self, k: int) -> list[Optional[torch.Tensor]]:
        while len(self.rollout) <= k:
            self.rollout.append([None] * self.num_branches)
            self._rollout_versions.append(0)
        self._rollout_versions[k] += 1  # the caller writes into the row
        return self.rollout[k]

    def write(self, b: int, k: int, d: torch.Tensor) -> None:
        """Branch b computed for every sample at step k."""
        self.version += 1
        if self.use_forward:
            self.forward[self.kind_of_branch[b]] = d
        if self.use_timestep:
            if self.forecast:
                slot = self.timestep[b]
                self.timestep[b] = (TaylorSlot(d, k, self.batch_dims[b]) if slot is None
                                    else slot.update(d, k, self.forecast))
            else:
                self.timestep[b] = d
        if self.use_rollout:
            self._rollout_row(k)[b] = d

    def write_rows(self, b: int, k: int, rows: torch.Tensor, d_rows: torch.Tensor, dim: int) -> None:
        """Branch b computed only for ``rows`` (indices along the batch dim ``dim``) at step k."""
        self.version += 1

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
            if self.forecast:
                slot = self.timestep[b]
                if slot is None:
                    merged(None)  # raises: never happens (step 0 computes every row)
                self.timestep[b] = slot.update_rows(rows, d_rows, k, self.forecast)
            else:
                self.timestep[b] = merged(self.timestep[b])
        if self.use_rollout:
            # A slot the previous call never filled (it ran fewer steps) stays empty: a partial
            # entry would be wrong for the other samples; the next call then computes (k, b).
            row = self._rollout_row(k)
            if row[b] is not None:
                row[b] = row[b].index_copy(dim, rows, d_rows)
