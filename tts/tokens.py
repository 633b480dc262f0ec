"""Token-wise partial refresh: ToCa- and DuCa-style plans (decision code ``TOKENS``).

Between full-compute steps (every ``n``-th step, as in FORA), a token-wise branch (the MLP: it acts
on every token independently) is recomputed for a fraction ``fresh_ratio`` of its tokens only; the
other tokens keep the branch output cached at the latest step (the timestep cache), and the
refreshed tokens are written back into that cache. Token-mixing branches (self-attention) reuse the
timestep cache whole on those steps: a subset of an attention output cannot be computed without
every token's keys and values. The engine gathers the chosen tokens, runs the branch on them only
(the skipped tokens are not computed) and scatters the result into a copy of the cached output.

Ideas from ToCa (Zou et al., ICLR 2025, "Accelerating Diffusion Transformers with Token-wise Feature
Caching") and DuCa (Zou et al. 2024, "Dual Feature Caching"); written from the papers' descriptions,
not their code. Which tokens to refresh, per sample, is a score plus a staleness bonus (ToCa's
"cache frequency" term: a token not refreshed for a while gains priority):

- ``score="attention"`` (ToCa): the attention a token *receives* in the same block's self-attention
  at the latest full step (mean over heads and queries). Needs attention probabilities, so the
  engine asks the block family's attention probe (:attr:`tts.spec.BranchSpec.probe`) for them at
  full steps (materialised attention maps: not FlashAttention-friendly; the summary's MACs count the
  attention products once, as for a fused kernel).
- ``score="duplicate"`` (DuCa-style, FlashAttention-friendly): tokens whose cached branch output is
  least similar (cosine) to the mean token output of their sample are refreshed first; redundant,
  near-duplicate tokens keep the cache. Costs O(N * D) per refresh, no attention maps.

``alternate=True`` (DuCa's dual caching) makes the steps between full computes alternate between
*aggressive* (reuse everything) and *conservative* (token refresh) steps; give it twice the fresh
ratio for the same compute.
"""
from __future__ import annotations

import math
from typing import Any, Optional, Sequence

import torch

from .plans import COMPUTE, TIMESTEP, TOKENS, Plan, check_sparsity

__all__ = ["TokenRefreshPlan", "toca", "duca", "fresh_ratio_for"]

SCORES = ("attention", "duplicate")


class TokenRefreshPlan(Plan):
    """Full compute every ``n`` steps; token-wise refresh of ``token_kinds`` branches in between."""

    def __init__(self, n: int, fresh_ratio: float, score: str = "attention", token_kinds: Sequence[str] = ("mlp",),
                 alternate: bool = False, staleness_weight: float = 0.5):
        if int(n) < 2:
            raise ValueError(f"interval n must be >= 2 (n=1 computes every step), got {n}")
        if not (0.0 < float(fresh_ratio) <= 1.0):
            raise ValueError(f"fresh_ratio must be in (0, 1], got {fresh_ratio}")
        if score not in SCORES:
            raise ValueError(f"unknown token score {score!r}; choose one of {SCORES}")
        self.n = int(n)
        self.fresh_ratio = float(fresh_ratio)
        self.score = score
        self.token_kinds = tuple(token_kinds)
        self.alternate = bool(alternate)
        self.staleness_weight = float(staleness_weight)
        self.wants_probe = score == "attention"
        self.uses = frozenset({COMPUTE, TIMESTEP, TOKENS})

    def bind(self, num_branches: int, branch_kinds: Sequence[str]) -> None:
        super().bind(num_branches, branch_kinds)
        if not any(k in self.token_kinds for k in branch_kinds):
            raise ValueError(f"{self.describe()}: the model has no branch of kind {self.token_kinds} "
                             f"(its kinds: {sorted(set(branch_kinds))})")
        self._rows: dict[int, torch.Tensor] = {}
        self.begin_call(0, 1)

    def begin_call(self, call_index: int, batch: int) -> None:
        self._last_full = 0
        self._fresh_at: dict[int, tuple] = {}  # branch -> (full step, [B, N] step of each token's last refresh)
        self._attention: dict[int, torch.Tensor] = {}  # site -> [B, N] attention received at the last full step

    def refresh_step(self, k: int) -> bool:
        """Whether token branches refresh at step ``k`` (else they reuse whole)."""
        off = k % self.n
        return off != 0 and (not self.alternate or off % 2 == 1)

    def step(self, k: int, batch: int) -> torch.Tensor:
        if k % self.n == 0:
            self._last_full = k
        row = self._rows.get(k)
        if row is None:
            if k % self.n == 0:
                codes = [COMPUTE] * self.num_branches
            else:
                tok = TOKENS if self.refresh_step(k) else TIMESTEP
                codes = [tok if kind in self.token_kinds else TIMESTEP for kind in self.branch_kinds]
            row = self._rows[k] = torch.tensor([codes], dtype=torch.int8)
        return row

    # ---------------------------------------------------------------- engine callbacks
    def record_probe(self, site: int, received: torch.Tensor) -> None:
        """Attention received per token [B, N] by the self-attention of block ``site`` (full steps)."""
        self._attention[site] = received.detach().float()

    def select_tokens(self, b: int, site: int, k: int, cached: torch.Tensor) -> torch.Tensor:
        """Indices [B, m] of the tokens of branch ``b`` to recompute at step ``k``; ``cached`` is the
        branch output held in the timestep cache [B, N, D]."""
        B, N = cached.shape[0], cached.shape[1]
        m = max(1, min(N, math.ceil(self.fresh_ratio * N)))
        entry = self._fresh_at.get(b)
        if entry is None or entry[0] != self._last_full or entry[1].shape != (B, N):
            fresh_at = torch.full((B, N), self._last_full, dtype=torch.long, device=cached.device)
        else:
            fresh_at = entry[1]
        if self.score == "attention":
            att = self._attention.get(site)
            if att is None or att.shape != (B, N):
                raise RuntimeError(f"{self.describe()}: no attention probe for block {site} at its last full step "
                                   "(the block family declares no BranchSpec.probe for its self-attention)")
            base = att.to(cached.device) / att.amax(1, keepdim=True).clamp_min(1e-12)
        else:
            c = cached.float()
            sim = torch.nn.functional.cosine_similarity(c, c.mean(1, keepdim=True), dim=-1)  # [B, N]
            base = (1.0 - sim) / (1.0 - sim).amax(1, keepdim=True).clamp_min(1e-12)
        stale = (k - fresh_at).float() / self.n
        idx = (base + self.staleness_weight * stale).topk(m, dim=1).indices
        self._fresh_at[b] = (self._last_full, fresh_at.scatter(1, idx, k))
        return idx

    def describe(self) -> str:
        kind = "duca" if self.alternate else "toca"
        return f"{kind}(n={self.n}, fresh_ratio={self.fresh_ratio:.3f}, score={self.score})"


def fresh_ratio_for(sparsity: float, n: int, token_share: float, alternate: bool = False) -> float:
    """The fresh ratio that makes a token-refresh plan compute ``1 - sparsity`` of the branch MACs,
    given the share of branch MACs in token-wise branches (e.g. MLP / (attention + MLP))."""
    check_sparsity(sparsity)
    refresh_steps = (n - 1) if not alternate else (n // 2)
    budget = (1.0 - sparsity) - 1.0 / n
    if budget <= 0 or refresh_steps == 0:
        raise ValueError(f"interval n={n} alone already computes {1 / n:.1%} >= {1 - sparsity:.1%}: "
                         "raise n for a token-refresh plan at this sparsity")
    r = budget * n / (refresh_steps * token_share)
    if r > 1:
        raise ValueError(f"sparsity {sparsity} with n={n} needs a fresh ratio {r:.2f} > 1: lower n")
    return r


def toca(n: int, fresh_ratio: float, **kw: Any) -> TokenRefreshPlan:
    """ToCa-style: attention-score token selection, refresh at every step between full computes."""
    return TokenRefreshPlan(n, fresh_ratio, score="attention", **kw)


def duca(n: int, fresh_ratio: float, **kw: Any) -> TokenRefreshPlan:
    """DuCa-style: similarity-based (FlashAttention-friendly) selection, aggressive/conservative alternation."""
    return TokenRefreshPlan(n, fresh_ratio, score=kw.pop("score", "duplicate"), alternate=True, **kw)
