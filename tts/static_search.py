"""Static schedules searched offline from activation similarity (a BAC-style baseline).

BAC ("Block-wise Adaptive Caching", Ji et al. 2025) measures, on calibration samples, how much each
block's output changes between denoising steps, and picks for every block the steps at which it is
recomputed so that the total change hidden by reuse is smallest. This module does the same for
tts branches, written from that description:

1. :func:`reuse_errors` runs dense sampling calls with every branch's output recorded at every
   step and returns ``E[b, j, i]``: the mean relative L1 error of serving step ``j`` of branch ``b``
   with its output from step ``i < j`` (what the timestep direction does).
2. :func:`search_schedule` chooses, per branch, exactly ``m = round((1 - sparsity) * K)`` compute
   steps (step 0 included) minimising the summed error, by dynamic programming over (number of
   computes, last compute step). Every branch gets the same budget, so the plan's sparsity equals
   the target; BAC's "bubbling union" refinement is not reproduced.

The result is a ``[K, nb]`` decision grid (compute / timestep) for :func:`tts.plans.from_tensor`.

:func:`search_compute_steps` is the output-error alternative for models where per-branch schedules
sample badly: one set of compute steps for every branch (whole steps reused, FORA-like, but placed
where they matter), found by local search that moves one compute step at a time while a
caller-supplied loss (e.g. L1 of the final sample against the dense one, same noise) decreases.
"""
from __future__ import annotations

from typing import Any, Callable, Optional, Sequence

import torch

from .plans import COMPUTE, TIMESTEP, Plan, check_sparsity

__all__ = ["record_branch_outputs", "reuse_errors", "search_schedule", "search_compute_steps", "steps_grid"]


class _ComputeAndKeep(Plan):
    """Computes every branch but declares timestep reuse, so the engine keeps each output in its
    timestep cache, where the recorder reads it after every step."""

    uses = frozenset({COMPUTE, TIMESTEP})

    def step(self, k: int, batch: int) -> torch.Tensor:
        return torch.zeros(1, self.num_branches, dtype=torch.int8)

    def describe(self) -> str:
        return "record"


def record_branch_outputs(model: Any, sample: Callable[[], None]) -> list[list[list[torch.Tensor]]]:
    """Every branch's output at every step of every dense sampling call that ``sample()`` runs on
    ``model`` (anything :func:`tts.accelerate` accepts): ``out[call][k][b]``, float32 copies with
    the batch dimension first."""
    from . import accelerate

    per_call: list[list[list[torch.Tensor]]] = []
    acc = accelerate(model, ("timestep",), plan=_ComputeAndKeep())
    seen: list = [None]

    def after_step(module, args, output):
        record = acc.calls[-1]  # the engine opens a new record at the first step of every call
        if record is not seen[0]:
            seen[0] = record
            per_call.append([])
        per_call[-1].append([t.detach().float().movedim(dim, 0).clone()  # batch first
                             for t, dim in zip(acc.cache.timestep, acc.cache.batch_dims)])

    handle = acc.target.denoiser.register_forward_hook(after_step)
    try:
        with torch.no_grad():
            sample()
    finally:
        handle.remove()
        acc.remove()
    if not per_call:
        raise ValueError("sample() ran no sampling call on the model")
    return per_call


def reuse_errors(model: Any, sample: Callable[[], None]) -> torch.Tensor:
    """``E[b, j, i]`` (float64, [nb, K, K], zero where i >= j) averaged over the samples of every
    dense sampling call that ``sample()`` runs on ``model``. All calls must have the same number of
    steps."""
    per_call = record_branch_outputs(model, sample)
    K = len(per_call[0])
    if any(len(c) != K for c in per_call):
        raise ValueError("all calibration calls must run the same number of denoising steps")
    nb = len(per_call[0][0])
    total = torch.zeros(nb, K, K, dtype=torch.float64)
    count = 0
    for call in per_call:
        for b in range(nb):
            x = torch.stack([call[k][b].reshape(call[k][b].shape[0], -1) for k in range(K)], dim=1)  # [B, K, n]
            diff = torch.cdist(x, x, p=1)  # [B, K(j), K(i)]
            norm = x.abs().sum(-1).clamp_min(1e-12)[:, :, None]  # ||x_j||_1
            total[b] += (diff / norm).sum(0).double()
        count += x.shape[0]
    return torch.tril(total / count, diagonal=-1)


def search_schedule(errors: torch.Tensor, sparsity: float) -> torch.Tensor:
    """Decision grid [K, nb] (int8: compute / timestep) with ``round((1 - sparsity) * K)`` computes
    per branch (at least 1: step 0), placed to minimise the summed reuse error of each branch."""
    sparsity = check_sparsity(sparsity)
    nb, K, _ = errors.shape
    m = max(1, min(K, round((1.0 - sparsity) * K)))
    out = torch.full((K, nb), TIMESTEP, dtype=torch.int8)
    inf = float("inf")
    for b in range(nb):
        e = errors[b].double()  # e[j, i]
        # seg[i, j] = cost of steps i+1..j all reusing step i's output
        seg = torch.cumsum(e.T * torch.triu(torch.ones(K, K, dtype=torch.float64), diagonal=1), dim=1)
        f = torch.full((m + 1, K), inf, dtype=torch.float64)
        arg = torch.zeros(m + 1, K, dtype=torch.long)
        f[1, 0] = 0.0
        for c in range(2, m + 1):
            for i in range(1, K):
                prev = f[c - 1, :i] + seg[:i, i - 1]
                j = int(torch.argmin(prev))
                f[c, i], arg[c, i] = prev[j], j
        final = f[m] + seg[:, K - 1]
        i = int(torch.argmin(final))
        for c in range(m, 0, -1):
            out[i, b] = COMPUTE
            i = int(arg[c, i])
    return out


def steps_grid(compute_steps: Sequence[int], steps: int, branches: int) -> torch.Tensor:
    """Decision grid [K, nb]: every branch computed at ``compute_steps``, timestep reuse elsewhere."""
    out = torch.full((steps, branches), TIMESTEP, dtype=torch.int8)
    out[list(compute_steps)] = COMPUTE
    return out


def search_compute_steps(loss: Callable[[list[int]], float], steps: int, computes: int, *,
                         init: Optional[Sequence[int]] = None, shifts: Sequence[int] = (1, 2, 3),
                         max_sweeps: int = 6, log: Optional[Callable[[str], None]] = None
                         ) -> tuple[list[int], list[dict]]:
    """Local search for ``computes`` compute steps out of ``steps`` (step 0 always included)
    minimising ``loss(sorted step list)``.

    Starts from ``init`` (default: evenly spaced, FORA's interval when it divides ``steps``). A sweep
    tries, for every compute step but 0, moving it by each of +-``shifts`` to a free step, and keeps a
    move as soon as it lowers the loss (first improvement). Stops after a sweep without improvement or
    ``max_sweeps``. Returns the best step list and the history of accepted moves (each with its loss).
    """
    if not 1 <= computes <= steps:
        raise ValueError(f"computes must lie in [1, {steps}], got {computes}")
    cur = sorted(set(init)) if init is not None else sorted({round(i * steps / computes) for i in range(computes)})
    if len(cur) != computes or cur[0] != 0 or cur[-1] >= steps:
        raise ValueError(f"init must hold {computes} distinct steps in [0, {steps}) including 0, got {cur}")
    best = float(loss(cur))
    history = [{"sweep": 0, "steps": list(cur), "loss": best}]
    say = log or (lambda msg: None)
    say(f"start {cur}: loss {best:.5f}")
    for sweep in range(1, max_sweeps + 1):
        improved = False
        for pos in range(1, computes):
            for d in [s * sign for s in shifts for sign in (-1, 1)]:
                new = cur[pos] + d
                if new <= 0 or new >= steps or new in cur:
                    continue
                cand = sorted(cur[:pos] + [new] + cur[pos + 1:])
                val = float(loss(cand))
                if val < best:
                    say(f"sweep {sweep}: {cur[pos]} -> {new}: loss {val:.5f}")
                    cur, best, improved = cand, val, True
                    history.append({"sweep": sweep, "steps": list(cur), "loss": best})
                    break
        if not improved:
            break
    return cur, history
