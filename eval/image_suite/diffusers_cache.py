"""diffusers' own caches on a DiT, as baselines in the same sampling loop as tts.

diffusers (0.42) ships training-free caches as model hooks (``diffusers.hooks``): First Block Cache
(FBCache, TeaCache-like: skip every block after the first when the first block's residual barely
changed), TaylorSeer (forecast hooked modules' outputs between full steps) and others. They run on
diffusers models: :class:`DiffusersCache` applies one of them to a DiT converted by
:func:`tts.adapters.dit_diffusers.to_diffusers` (:class:`~tts.adapters.dit_diffusers.DiffusersDiT`),
with per-call state, decision counts and MACs.

``DiTTransformer2DModel`` is not a ``CacheMixin`` in diffusers 0.42 (no ``enable_cache`` /
``cache_context``), so the hooks are applied with ``diffusers.hooks.apply_*`` and the cache context
that a diffusers pipeline would set per call is set here (one context, ``"cond"``: the CFG halves
are one batch, as in diffusers' DiT pipeline).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import torch
import torch.nn as nn

from tts.adapters.dit_diffusers import DiffusersDiT

__all__ = ["DiffusersCache", "CacheCall", "calibrate_fbc_threshold", "DIFFUSERS_CACHES"]

DIFFUSERS_CACHES = ("fbc", "taylorseer")


@dataclass
class CacheCall:
    """Counts of one sampling call: branch executions and MACs inside the transformer blocks."""

    forwards: int = 0
    computed: int = 0  # attn1 / ff branch executions
    macs: float = 0.0
    forward_macs: list = field(default_factory=list)

    def sparsity(self, depth: int) -> float:
        """Fraction of the (step, block, branch) decisions not computed."""
        return 1.0 - self.computed / max(2 * depth * self.forwards, 1)

    def macs_dense(self) -> float:
        """Dense MACs of the call: its full forward (step 0 always computes) times its forwards."""
        return max(self.forward_macs, default=0.0) * self.forwards


class DiffusersCache:
    """One of diffusers' caches applied to a :class:`DiffusersDiT`, with per-call state and counts.

    kind ``"fbc"``: ``FirstBlockCacheConfig(threshold)``. ``"taylorseer"``:
    ``TaylorSeerCacheConfig(cache_interval=interval, max_order=order, disable_cache_before_step=warmup,
    taylor_factors_dtype=float32)`` on every block's ``attn1`` and ``ff`` (diffusers' default
    patterns ``^transformer_blocks.*attn`` match no DiT module name under ``re.fullmatch``).
    Counting: forward hooks on every ``nn.Linear`` of the blocks (MACs = tokens x in x out) and on
    ``attn1.to_q`` (attention products 2 x B x N^2 x D, and an attention execution) and ``ff.net.2``
    (an MLP execution): a branch whose hook returned the cached value runs none of them.
    """

    def __init__(self, model: DiffusersDiT, kind: str, *, threshold: float = 0.05, interval: int = 5,
                 order: int = 1, warmup: int = 1):
        from diffusers.hooks import (FirstBlockCacheConfig, HookRegistry, TaylorSeerCacheConfig,
                                     apply_first_block_cache, apply_taylorseer_cache)

        if kind not in DIFFUSERS_CACHES:
            raise ValueError(f"unknown diffusers cache {kind!r}; choose from {DIFFUSERS_CACHES}")
        if not isinstance(model, DiffusersDiT):
            raise TypeError("DiffusersCache needs a DiffusersDiT (DiffusersDiT.from_dit(model))")
        self.model, self.kind = model, kind
        tr = model.transformer
        self.depth = len(tr.transformer_blocks)
        if kind == "fbc":
            if threshold < 0:
                raise ValueError(f"threshold must be >= 0, got {threshold}")
            self.config = FirstBlockCacheConfig(threshold=threshold)
            apply_first_block_cache(tr, self.config)
        else:
            if interval < 1 or order < 0 or warmup < 1:
                raise ValueError("taylorseer needs interval >= 1, order >= 0, warmup >= 1 (step 0 must compute)")
            self.config = TaylorSeerCacheConfig(
                cache_interval=interval, max_order=order, disable_cache_before_step=warmup,
                taylor_factors_dtype=torch.float32,
                cache_identifiers=[r"transformer_blocks\.\d+\.attn1", r"transformer_blocks\.\d+\.ff"])
            apply_taylorseer_cache(tr, self.config)
        self._registry = HookRegistry.check_if_exists_or_initialize(tr)
        self._registry.invalidate_child_registries_cache()  # the block hooks just added
        self.calls: list[CacheCall] = []
        self._handles = []
        self._in_forward = False
        self._hook_counts(tr)
        model.on_call_start.append(self._start_call)

    # ------------------------------------------------------------------------------ counting
    def _hook_counts(self, tr: nn.Module) -> None:
        def linear(mod, inp, out):
            if self._in_forward:  # not condition_memory's embedder calls
                self.calls[-1].macs += out.numel() // mod.out_features * mod.in_features * mod.out_features

        def attention(mod, inp, out):
            b, n, d = inp[0].shape
            self.calls[-1].computed += 1
            self.calls[-1].macs += 2 * b * n * n * d

        def mlp(mod, inp, out):
            self.calls[-1].computed += 1

        def forward_start(mod, args, kwargs):
            if not self.calls:
                raise RuntimeError("DiffusersCache: call the model through sample_dit (a sampling call starts "
                                   "with condition_memory, where the cache state is reset)")
            self._in_forward = True
            call = self.calls[-1]
            call.forwards += 1
            call.forward_macs.append(call.macs)

        def forward_end(mod, args, kwargs, out):
            self._in_forward = False
            call = self.calls[-1]
            call.forward_macs[-1] = call.macs - call.forward_macs[-1]

        for name, mod in tr.transformer_blocks.named_modules():
            if isinstance(mod, nn.Linear):
                self._handles.append(mod.register_forward_hook(linear))
            if re.fullmatch(r"\d+\.attn1\.to_q", name):
                self._handles.append(mod.register_forward_hook(attention))
            if re.fullmatch(r"\d+\.ff\.net\.2", name):
                self._handles.append(mod.register_forward_hook(mlp))
        self._handles.append(tr.register_forward_pre_hook(forward_start, with_kwargs=True))
        self._handles.append(tr.register_forward_hook(forward_end, with_kwargs=True))

    def _start_call(self) -> None:
        from diffusers.hooks.hooks import CacheContext, _set_cache_context

        self._registry.reset_stateful_hooks()  # also clears the context
        _set_cache_context(self.model.transformer, CacheContext("cond"))
        self.calls.append(CacheCall())

    # ---------------------------------------------------------------------------------- API
    def describe(self) -> str:
        if self.kind == "fbc":
            return f"diffusers FirstBlockCache(threshold={self.config.threshold:g})"
        c = self.config
        return (f"diffusers TaylorSeer(interval={c.cache_interval}, order={c.max_order}, "
                f"warmup={c.disable_cache_before_step}, attn1+ff)")

    def last_call(self) -> CacheCall:
        if not self.calls:
            raise RuntimeError("no sampling call yet")
        return self.calls[-1]

    def remove(self) -> None:
        """Remove the diffusers hooks and the counters; the model computes densely again."""
        from diffusers.hooks.hooks import _set_cache_context

        for h in self._handles:
            h.remove()
        self._handles.clear()
        self._registry.reset_stateful_hooks()
        for module in self.model.transformer.modules():  # the transformer itself and every hooked block
            reg = getattr(module, "_diffusers_hook", None)
            if reg is not None:
                for name in list(reg._hook_order):
                    reg.remove_hook(name, recurse=False)
        self._registry.invalidate_child_registries_cache()
        _set_cache_context(self.model.transformer, None)
        if self._start_call in self.model.on_call_start:
            self.model.on_call_start.remove(self._start_call)


def calibrate_fbc_threshold(model: DiffusersDiT, target: float, labels: torch.Tensor, noise: torch.Tensor, *,
                            steps: int = 50, cfg_scale: float = 1.5, iters: int = 12,
                            high: float = 4.0) -> tuple[float, float]:
    """The FBCache threshold whose sparsity on a calibration batch is closest to ``target``.

    Bisection on the threshold (FBCache's skipped fraction grows with it; its ceiling is
    ``(depth - 1) / depth`` of the branches, the first block always computes). Returns
    ``(threshold, sparsity reached)``. Use labels and noise that the evaluation never sees.
    """
    from tts.adapters.dit import sample_dit

    if not 0.0 <= target < 1.0:
        raise ValueError(f"target sparsity must lie in [0, 1), got {target}")

    def measure(th: float) -> float:
        cache = DiffusersCache(model, "fbc", threshold=th)
        try:
            sample_dit(model, labels, steps=steps, cfg_scale=cfg_scale, noise=noise)
            return cache.last_call().sparsity(cache.depth)
        finally:
            cache.remove()

    lo, hi = 0.0, high
    best = (lo, measure(lo))
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        s = measure(mid)
        if abs(s - target) < abs(best[1] - target) or (abs(s - target) == abs(best[1] - target) and mid < best[0]):
            best = (mid, s)
        if s < target:
            lo = mid
        else:
            hi = mid
    return best
