"""Gate scheduler: pruner logits -> decisions, plus an exact-budget mode.

Logits have shape [B, K, nb, O] over the options ``codes`` (``codes[0]`` is always compute, the
rest are the enabled reuse directions in canonical order). Step 0 is always compute.

- :func:`ste_gates` (training): softmax, step 0 replaced by one-hot(compute), straight-through
  one-hot: the forward value is exactly one-hot, the gradient w.r.t. the probabilities is identity.
- :func:`argmax_codes` (the paper's test-time rule): argmax per (k, b); realised sparsity varies
  with the observation.
- :func:`budget_codes` (beyond the paper): per sample, rank every (k, b) by its compute
  probability and compute exactly the top ``round((1 - sparsity) * K * nb)`` (step 0 counts towards
  the budget and is always kept); the other decisions take their best reuse direction. One trained
  pruner then serves any target sparsity. ``whole_steps=True`` (a pruner with tied branches) ranks
  steps instead and computes the top ``round((1 - sparsity) * K)`` of them with every branch.
"""
from __future__ import annotations

from typing import Sequence, Union

import torch

from .plans import COMPUTE, check_sparsity

__all__ = ["ste_gates", "budget_ste_gates", "argmax_codes", "budget_codes", "reuse_fraction"]


def _force_first(p: torch.Tensor) -> torch.Tensor:
    first = torch.zeros_like(p[:, :1])
    first[..., 0] = 1.0
    return torch.cat([first, p[:, 1:]], dim=1)


def ste_gates(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(hard straight-through gates, soft probabilities), both [B, K, nb, O]."""
    p = _force_first(logits.float().softmax(-1))
    hard = torch.nn.functional.one_hot(p.argmax(-1), p.shape[-1]).to(p.dtype)
    return hard - p.detach() + p, p


def _budget_options(p: torch.Tensor, sparsity: float, whole_steps: bool = False) -> torch.Tensor:
    """Option per (sample, step, branch) computing exactly the top ``1 - sparsity`` by compute
    probability (step 0 always), the most likely reuse direction elsewhere: [B, K, nb]. With
    ``whole_steps`` the unit is a step (score: its branches' mean compute probability)."""
    sparsity = check_sparsity(sparsity)
    B, K, nb, O = p.shape
    if O < 2:
        raise ValueError("budget mode needs at least one reuse direction")
    score = p[..., 0].detach().clone()
    if whole_steps:
        score = score.mean(2, keepdim=True)
    score[:, 0] = float("inf")  # step 0 always computes
    units = score.shape[2]
    keep = max(units, min(K * units, round((1.0 - sparsity) * K * units)))
    flat = score.reshape(B, K * units)
    top = flat.topk(keep, dim=1).indices
    compute = torch.zeros_like(flat, dtype=torch.bool).scatter_(1, top, True).reshape(B, K, units).expand(B, K, nb)
    reuse_option = p[..., 1:].detach().argmax(-1) + 1
    return torch.where(compute, torch.zeros_like(reuse_option), reuse_option)


def budget_ste_gates(logits: torch.Tensor, sparsity: float, whole_steps: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Straight-through gates whose forward is the exact-budget decision (:func:`budget_codes`):
    training sees the test-time rule, the realised sparsity is fixed, and the gradient only
    re-ranks which branches compute. Returns (hard gates, soft probabilities), [B, K, nb, O]."""
    p = _force_first(logits.float().softmax(-1))
    hard = torch.nn.functional.one_hot(_budget_options(p, sparsity, whole_steps), p.shape[-1]).to(p.dtype)
    return hard - p.detach() + p, p


def reuse_fraction(gates: torch.Tensor) -> torch.Tensor:
    """Per-sample fraction of (k, b) decisions that reuse: [B] (differentiable through STE gates)."""
    return 1.0 - gates[..., 0].mean(dim=(1, 2))


Codes = Union[Sequence[int], torch.Tensor]  # option -> decision code; a tensor table on the logits' device


def _to_codes(option: torch.Tensor, codes: Codes) -> torch.Tensor:
    if torch.is_tensor(codes):  # prebuilt on the device: no host->device copy (which would sync a stream)
        return codes[option]
    table = torch.tensor(list(codes), dtype=torch.int8, device=option.device)
    return table[option]


def argmax_codes(logits: torch.Tensor, codes: Codes) -> torch.Tensor:
    """Decision codes [B, K, nb] (int8) by argmax, step 0 forced to compute."""
    option = logits.argmax(-1)
    option[:, 0] = 0
    return _to_codes(option, codes)


def budget_codes(logits: torch.Tensor, codes: Codes, sparsity: float, whole_steps: bool = False) -> torch.Tensor:
    """Decision codes [B, K, nb] computing exactly ``round((1 - sparsity) * K * nb)`` branches per
    sample (never fewer than step 0's nb), ranked by compute probability; with ``whole_steps``,
    exactly ``round((1 - sparsity) * K)`` whole steps."""
    return _to_codes(_budget_options(logits.float().softmax(-1), sparsity, whole_steps), codes)


assert COMPUTE == 0  # option 0 of every head is compute
