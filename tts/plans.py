"""Plans: a decision per (sample, denoising step, branch): compute, or reuse from a direction.

Decision codes (also the pruner head's option order, as in the paper's mask M = (C, F, T, R)):

====  ==========  ==================================================================================
code  name        meaning
====  ==========  ==================================================================================
0     compute     run the branch; refresh the forward/timestep/rollout caches with its output
1     forward     reuse the latest computed branch of the same kind earlier in this forward
                  (it wraps around to the previous step's last blocks: "zig-zag")
2     timestep    reuse this branch at the most recent step of this call where it was computed
3     rollout     reuse this branch at the same step index in the previous sampling call of the episode
4     tokens      recompute only some tokens of a token-wise branch, the rest from the timestep cache
                  (token-refresh plans, :mod:`tts.tokens`; not a pruner option)
====  ==========  ==================================================================================

A plan never needs to know the number of steps in advance: the engine asks it for step ``k`` as the
sampling loop reaches it. Step 0 (and the first call of an episode when the rollout direction is on)
is always computed by the engine, whatever the plan says.
"""
from __future__ import annotations

import math
from types import MappingProxyType
from typing import Iterable, Mapping, Optional, Sequence, Union

import torch

__all__ = [
    "COMPUTE",
    "FORWARD",
    "TIMESTEP",
    "ROLLOUT",
    "TOKENS",
    "DIRECTIONS",
    "CODE_NAMES",
    "Plan",
    "DensePlan",
    "IntervalPlan",
    "UniformPlan",
    "RotatingPlan",
    "TensorPlan",
    "dense",
    "every_n",
    "uniform",
    "rotating",
    "from_tensor",
    "check_directions",
    "check_sparsity",
]

COMPUTE, FORWARD, TIMESTEP, ROLLOUT, TOKENS = 0, 1, 2, 3, 4
DIRECTIONS = {"forward": FORWARD, "timestep": TIMESTEP, "rollout": ROLLOUT}
CODE_NAMES = ("compute", "forward", "timestep", "rollout", "tokens")
_LETTERS = {"C": COMPUTE, "F": FORWARD, "T": TIMESTEP, "R": ROLLOUT}


def check_directions(directions: Iterable[str]) -> tuple[str, ...]:
    """Validate direction names; returns them in canonical order."""
    if isinstance(directions, str):
        directions = (directions,)
    names = tuple(directions)
    unknown = [d for d in names if d not in DIRECTIONS]
    if unknown:
        raise ValueError(
            f"unknown direction(s) {unknown}; choose any subset of {tuple(DIRECTIONS)}"
        )
    return tuple(d for d in DIRECTIONS if d in names)


def check_sparsity(sparsity: float) -> float:
    """Sparsity is the fraction of (step, branch) decisions that reuse; it must lie in [0, 1)."""
    s = float(sparsity)
    if not (0.0 <= s < 1.0) or math.isnan(s):
        raise ValueError(f"sparsity must be in [0, 1), got {sparsity!r}")
    return s


def _accumulator_hits(i: int, rate: float) -> bool:
    """True at evenly spread indices with density ``rate``; index 0 always hits."""
    eps = 1e-9
    return math.floor(i * rate + eps) > math.floor((i - 1) * rate + eps)


class Plan:
    """Base class of decision sources: the whole protocol the engine calls, with no-op defaults.

    Subclasses implement :meth:`step`; everything else is optional. Per sampling call the engine
    calls, in this order: :meth:`observe` (plans that read the condition memory, before the call),
    :meth:`begin_call`, then :meth:`step` (or :meth:`soft_step` for ``soft`` plans) once per
    denoising step from step 1 on (step 0 always computes), and during a step
    :meth:`record_probe` / :meth:`select_tokens` for token-refresh plans.

    ``step(k, batch)`` returns an int8 CPU tensor of shape [1, nb] (same for every sample) or
    [batch, nb]. ``uses`` is the set of decision codes the plan may emit (validated against the
    enabled directions when the plan is bound).
    """

    #: decision codes the plan may emit
    uses: frozenset[int] = frozenset({COMPUTE})
    #: decision code of each gate option of :meth:`soft_step` (compute first)
    codes: Sequence[int] = (COMPUTE,)
    #: True for training plans: every branch computes and is mixed with cached outputs by the
    #: differentiable gates of :meth:`soft_step` instead of :meth:`step`'s hard decisions
    soft: bool = False
    #: True when the plan wants each self-attention's received attention (:meth:`record_probe`)
    wants_probe: bool = False
    #: seconds the plan spent on the current call (e.g. ``pruner``, ``wait``), read after step 1
    timing: Mapping[str, float] = MappingProxyType({})
    #: MACs the plan itself spends per sample and call (a learned pruner); 0 for static plans
    macs_per_sample: float = 0.0
    #: the number of denoising steps the plan was made for (None: any); a call that runs fewer is
    #: reported (a call that runs more raises at the first step the plan lacks)
    num_steps: Optional[int] = None

    def bind(self, num_branches: int, branch_kinds: Sequence[str]) -> None:
        """Called once by the engine with the model's branch layout."""
        self.num_branches = num_branches
        self.branch_kinds = tuple(branch_kinds)

    @property
    def reads_condition(self) -> bool:
        """True when the plan overrides :meth:`observe`: the model must expose its condition memory."""
        return type(self).observe is not Plan.observe

    def observe(self, memory: torch.Tensor, dense: bool) -> None:
        """The condition memory [B, K, Tc, D] of the call about to start (all K steps). ``dense``:
        the engine computes this call fully anyway (first call of an episode)."""

    def begin_call(self, call_index: int, batch: int) -> None:
        """Called at the start of every sampling call (before step 0); ``call_index`` counts every
        call since the accelerator was installed."""

    def step(self, k: int, batch: int) -> torch.Tensor:  # pragma: no cover - abstract
        """Decisions for step ``k``: int8 [1 or batch, num_branches]."""
        raise NotImplementedError

    def soft_step(self, k: int) -> torch.Tensor:
        """``soft`` plans: gates [B, num_branches, len(codes)] for step ``k`` (option j reuses ``codes[j]``)."""
        raise NotImplementedError(f"{self.describe()} is not a soft (training) plan")

    def record_probe(self, site: int, received: torch.Tensor) -> None:
        """``wants_probe`` plans: attention received per token [B, N] in block ``site`` at a computed step."""

    def select_tokens(self, b: int, site: int, k: int, cached: torch.Tensor) -> torch.Tensor:
        """Plans emitting ``TOKENS``: indices [B, m] of the tokens of branch ``b`` to recompute at step
        ``k``; ``cached`` is its timestep-cache output [B, N, ...]."""
        raise NotImplementedError(f"{self.describe()} emits no token-wise refresh")

    @property
    def may_reuse(self) -> bool:
        """Whether any decision reuses (the engine then keeps caches)."""
        return bool(self.uses - {COMPUTE})

    def describe(self) -> str:
        """Short label for summaries and error messages."""
        return type(self).__name__


class _PerStepPlan(Plan):
    """A plan identical for every sample and every call: rows are memoised per step."""

    def bind(self, num_branches: int, branch_kinds: Sequence[str]) -> None:
        super().bind(num_branches, branch_kinds)
        self._rows: dict[int, torch.Tensor] = {}

    def step(self, k: int, batch: int) -> torch.Tensor:
        row = self._rows.get(k)
        if row is None:
            row = torch.tensor([self._row(k)], dtype=torch.int8)
            self._rows[k] = row
        return row

    def _row(self, k: int) -> list[int]:  # pragma: no cover - abstract
        raise NotImplementedError


class DensePlan(_PerStepPlan):
    """Compute every branch at every step (the model's outputs stay bit-identical)."""

    uses = frozenset({COMPUTE})

    def _row(self, k: int) -> list[int]:
        return [COMPUTE] * self.num_branches

    def describe(self) -> str:
        return "dense"


class IntervalPlan(_PerStepPlan):
    """FORA-style: compute every branch at steps k % n == 0, reuse ``direction`` in between."""

    def __init__(self, n: int, direction: str = "timestep"):
        if int(n) < 1:
            raise ValueError(f"interval n must be >= 1, got {n}")
        self.n = int(n)
        (self.direction,) = check_directions((direction,))
        self.uses = frozenset({COMPUTE, DIRECTIONS[self.direction]})

    def _row(self, k: int) -> list[int]:
        code = COMPUTE if k % self.n == 0 else DIRECTIONS[self.direction]
        return [code] * self.num_branches

    def describe(self) -> str:
        return f"every_n(n={self.n}, {self.direction})"


class UniformPlan(_PerStepPlan):
    """Single-direction static schedule at a target sparsity, compute spread evenly.

    - ``timestep`` / ``rollout``: whole steps are computed at evenly spaced step indices (a
      fractional FORA interval), the others reuse that direction for every branch.
    - ``forward``: every step computes the same evenly spaced subset of blocks per branch kind (the
      first block of each kind always computes), the others reuse the latest computed block of their
      kind in the same forward.
    """

    def __init__(self, sparsity: float, direction: str = "timestep"):
        self.sparsity = check_sparsity(sparsity)
        (self.direction,) = check_directions((direction,))
        self.uses = frozenset({COMPUTE, DIRECTIONS[self.direction]})

    def _row(self, k: int) -> list[int]:
        rate = 1.0 - self.sparsity
        code = DIRECTIONS[self.direction]
        if self.direction != "forward":
            return [COMPUTE if _accumulator_hits(k, rate) else code] * self.num_branches
        row, seen = [], {}
        for kind in self.branch_kinds:
            i = seen.get(kind, 0)
            seen[kind] = i + 1
            row.append(COMPUTE if _accumulator_hits(i, rate) else code)
        return row

    def describe(self) -> str:
        return f"uniform(sparsity={self.sparsity}, {self.direction})"


class RotatingPlan(Plan):
    """Whole-step schedule whose compute steps move by one step per sampling call.

    At call ``c``, step ``k`` computes where :class:`UniformPlan` would compute step ``k + c``, and
    every other step reuses ``direction``. With the rollout direction, each (step, branch) slot of
    the rollout cache is then refreshed about every ``1 / (1 - sparsity)`` calls; a static schedule
    refreshes the reused slots never (the cache writes a slot only when it computes), so they keep
    the episode's first-call features. Sparsity per call equals the static schedule's up to one step
    (step 0 always computes).
    """

    def __init__(self, sparsity: float, direction: str = "rollout"):
        self.sparsity = check_sparsity(sparsity)
        (self.direction,) = check_directions((direction,))
        if self.direction == "forward":
            raise ValueError("a rotating schedule moves whole compute steps: use the timestep or rollout direction")
        self.uses = frozenset({COMPUTE, DIRECTIONS[self.direction]})
        self._offset = 0
        self._rows: dict[tuple[int, int], torch.Tensor] = {}

    def begin_call(self, call_index: int, batch: int) -> None:
        self._offset = call_index

    def step(self, k: int, batch: int) -> torch.Tensor:
        key = (k, self._offset)
        row = self._rows.get(key)
        if row is None:
            if len(self._rows) > 4096:
                self._rows.clear()
            hit = _accumulator_hits(k + self._offset, 1.0 - self.sparsity)
            row = self._rows[key] = torch.full((1, self.num_branches), COMPUTE if hit else DIRECTIONS[self.direction],
                                               dtype=torch.int8)
        return row

    def describe(self) -> str:
        return f"rotating(sparsity={self.sparsity}, {self.direction})"


class TensorPlan(Plan):
    """An explicit decision tensor: [K, nb] (all samples) or [B, K, nb], ints or 'CFTR' letters."""

    def __init__(self, decisions: Union[torch.Tensor, Sequence]):
        if isinstance(decisions, (list, tuple)) and decisions and _is_letters(decisions):
            decisions = _letters_to_codes(decisions)
        t = torch.as_tensor(decisions)
        if t.dtype.is_floating_point or t.dtype == torch.bool:
            raise TypeError(f"decision tensor must hold integer codes 0..3, got dtype {t.dtype}")
        if t.dim() == 2:
            t = t.unsqueeze(0)
        if t.dim() != 3:
            raise ValueError(
                f"decision tensor must have shape [K, num_branches] or [B, K, num_branches], "
                f"got {tuple(t.shape)}"
            )
        if t.numel() and (t.min() < 0 or t.max() > 3):
            raise ValueError("decision codes must be in 0..3 (compute, forward, timestep, rollout)")
        self.decisions = t.to(torch.int8).cpu().contiguous()
        self.uses = frozenset(int(c) for c in torch.unique(self.decisions).tolist())
        self.num_steps = int(self.decisions.shape[1])

    def bind(self, num_branches: int, branch_kinds: Sequence[str]) -> None:
        super().bind(num_branches, branch_kinds)
        if self.decisions.shape[-1] != num_branches:
            raise ValueError(
                f"plan has {self.decisions.shape[-1]} branches per step but the model has "
                f"{num_branches} (blocks x branches); plan shape {tuple(self.decisions.shape)}"
            )
        self._rows: dict[int, torch.Tensor] = {}

    def step(self, k: int, batch: int) -> torch.Tensor:
        nsteps = self.decisions.shape[1]
        if k >= nsteps:
            raise IndexError(
                f"the sampling loop reached step {k} but the plan only has {nsteps} steps"
            )
        rows = self._rows.get(k)
        if rows is None:  # one tensor per step, so the engine's per-step preprocessing is reused
            rows = self._rows[k] = self.decisions[:, k]
        if rows.shape[0] not in (1, batch):
            raise ValueError(
                f"plan holds decisions for {rows.shape[0]} samples but the batch has {batch}"
            )
        return rows

    def describe(self) -> str:
        return f"tensor{tuple(self.decisions.shape)}"


def _is_letters(x) -> bool:
    while isinstance(x, (list, tuple)) and x:
        x = x[0]
    return isinstance(x, str)


def _letters_to_codes(x):
    if isinstance(x, str):
        try:
            return [_LETTERS[c] for c in x]
        except KeyError as e:
            raise ValueError(f"unknown decision letter {e.args[0]!r}; use C, F, T or R") from None
    return [_letters_to_codes(v) for v in x]


def dense() -> DensePlan:
    """Compute everything."""
    return DensePlan()


def every_n(n: int, direction: str = "timestep") -> IntervalPlan:
    """FORA-style: full compute every ``n`` steps, reuse ``direction`` otherwise."""
    return IntervalPlan(n, direction)


def uniform(sparsity: float, direction: str = "timestep") -> UniformPlan:
    """Single-direction schedule reusing a fraction ``sparsity`` of branches along ``direction``."""
    return UniformPlan(sparsity, direction)


def rotating(sparsity: float, direction: str = "rollout") -> RotatingPlan:
    """Whole compute steps spread evenly, moved by one step per call (refreshes rollout slots)."""
    return RotatingPlan(sparsity, direction)


def from_tensor(decisions: Union[torch.Tensor, Sequence]) -> TensorPlan:
    """Explicit decisions [K, nb] or [B, K, nb] (codes 0..3 or strings of 'CFTR')."""
    return TensorPlan(decisions)
