"""diffusers' own caches on a DiT, as baselines in the same sampling loop as tts.

diffusers (0.42) ships training-free caches as model hooks (``diffusers.hooks``): First Block Cache
(FBCache, TeaCache-like: skip every block after the first when the first block's residual barely
changed), TaylorSeer (forecast hooked modules' outputs between full steps) and others. They run on
diffusers models, so this module

- converts an official-layout :class:`~tts.adapters.dit.DiT` into a diffusers
  ``DiTTransformer2DModel`` with the same function (:func:`to_diffusers`; float round-off only: the
  timestep features are switched to the official frequencies, see there),
- wraps it with the official calling convention (:class:`DiffusersDiT`), so
  :func:`~tts.adapters.dit.sample_dit` samples it with the same noise, scheduler and batched CFG as
  every tts method, and
- applies one of diffusers' caches with per-call state, decision counts and MACs
  (:class:`DiffusersCache`),
- loads a diffusers DiT from a local folder (a ``DiTPipeline`` folder such as facebook/DiT-XL-2-256,
  or its ``transformer`` folder) as a :class:`DiffusersDiT` (:func:`load_diffusers_dit`; what
  :func:`~tts.adapters.dit.load_dit` does for a directory), which ``tts.accelerate`` and
  :func:`~tts.adapters.dit.sample_dit` take like an official-layout DiT (batched CFG [cond; uncond],
  condition memory for a pruner).

``DiTTransformer2DModel`` is not a ``CacheMixin`` in diffusers 0.42 (no ``enable_cache`` /
``cache_context``), so the hooks are applied with ``diffusers.hooks.apply_*`` and the cache context
that a diffusers pipeline would set per call is set here (one context, ``"cond"``: the CFG halves
are one batch, as in diffusers' DiT pipeline).
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

import torch
import torch.nn as nn

from tts.adapters.dit import DiT, DiTConfig
from tts.spec import Target, register_model_adapter

__all__ = ["to_diffusers", "DiffusersDiT", "DiffusersCache", "load_diffusers_dit", "calibrate_fbc_threshold",
           "DIFFUSERS_CACHES"]

DIFFUSERS_CACHES = ("fbc", "taylorseer")


def to_diffusers(model: DiT) -> "Any":
    """A diffusers ``DiTTransformer2DModel`` computing the same function as ``model`` (eval mode).

    Parameter map (official -> diffusers): ``x_embedder.proj`` -> ``pos_embed.proj``; per block
    ``attn.qkv`` -> ``attn1.to_q/k/v``, ``attn.proj`` -> ``attn1.to_out.0``, ``mlp.fc1/fc2`` ->
    ``ff.net.0.proj`` / ``ff.net.2``, ``adaLN_modulation.1`` -> ``norm1.linear``, and the shared
    ``t_embedder`` / ``y_embedder`` copied into every block's ``norm1.emb`` (diffusers embeds the
    condition in each block); ``final_layer.adaLN_modulation.1`` / ``final_layer.linear`` ->
    ``proj_out_1`` / ``proj_out_2``. The fixed position embedding is copied, LayerNorm eps set to the
    official 1e-6, and each block's timestep features use the official frequencies
    (``downscale_freq_shift = 0``; diffusers' DiT default of 1 divides by ``half - 1``). Neither of
    these two survives ``save_pretrained``: diffusers rebuilds the (standard, never trained) sin-cos
    positions and its own timestep features when it loads a folder.
    """
    from diffusers import DiTTransformer2DModel

    cfg = model.config
    if cfg.hidden_size % cfg.num_heads:
        raise ValueError(f"hidden size {cfg.hidden_size} is not divisible by {cfg.num_heads} heads")
    if cfg.class_dropout_prob <= 0:
        raise ValueError("diffusers' DiT always has the null class (class_dropout_prob > 0); this DiT has none")
    out = DiTTransformer2DModel(
        num_attention_heads=cfg.num_heads, attention_head_dim=cfg.hidden_size // cfg.num_heads,
        in_channels=cfg.in_channels, out_channels=model.out_channels, num_layers=cfg.depth,
        sample_size=cfg.input_size, patch_size=cfg.patch_size, num_embeds_ada_norm=cfg.num_classes,
        norm_eps=1e-6,
    )
    if int(out.transformer_blocks[0].ff.net[0].proj.out_features) != int(cfg.hidden_size * cfg.mlp_ratio):
        raise ValueError(f"diffusers' DiT has mlp ratio 4; this DiT has {cfg.mlp_ratio}")
    src = model.state_dict()
    dst: dict[str, torch.Tensor] = {
        "pos_embed.proj.weight": src["x_embedder.proj.weight"],
        "pos_embed.proj.bias": src["x_embedder.proj.bias"],
        "proj_out_1.weight": src["final_layer.adaLN_modulation.1.weight"],
        "proj_out_1.bias": src["final_layer.adaLN_modulation.1.bias"],
        "proj_out_2.weight": src["final_layer.linear.weight"],
        "proj_out_2.bias": src["final_layer.linear.bias"],
    }
    emb = {"timestep_embedder.linear_1": "t_embedder.mlp.0", "timestep_embedder.linear_2": "t_embedder.mlp.2"}
    for i in range(cfg.depth):
        b, o = f"transformer_blocks.{i}.", f"blocks.{i}."
        for part, (w, bias) in zip(("to_q", "to_k", "to_v"),
                                   zip(src[o + "attn.qkv.weight"].chunk(3), src[o + "attn.qkv.bias"].chunk(3))):
            dst[b + f"attn1.{part}.weight"], dst[b + f"attn1.{part}.bias"] = w, bias
        pairs = {"attn1.to_out.0": o + "attn.proj", "ff.net.0.proj": o + "mlp.fc1", "ff.net.2": o + "mlp.fc2",
                 "norm1.linear": o + "adaLN_modulation.1"}
        pairs.update({f"norm1.emb.{k}": v for k, v in emb.items()})
        for new, old in pairs.items():
            dst[b + new + ".weight"], dst[b + new + ".bias"] = src[old + ".weight"], src[old + ".bias"]
        dst[b + "norm1.emb.class_embedder.embedding_table.weight"] = src["y_embedder.embedding_table.weight"]
    missing, unexpected = out.load_state_dict(dst, strict=False)
    missing = [k for k in missing if not k.endswith("pos_embed.pos_embed")]
    if missing or unexpected:  # a diffusers release that renamed something
        raise RuntimeError(f"official -> diffusers DiT map is incomplete: missing {missing[:5]}, "
                           f"unexpected {unexpected[:5]}")
    out.pos_embed.pos_embed.data.copy_(model.pos_embed.data)
    for block in out.transformer_blocks:
        block.norm1.emb.time_proj.downscale_freq_shift = 0
    return out.to(model.pos_embed.device).eval()


class DiffusersDiT(nn.Module):
    """A diffusers ``DiTTransformer2DModel`` with the official DiT calling convention of
    :func:`~tts.adapters.dit.sample_dit`: ``forward(x, t, y, c=None)``, ``condition_memory``,
    ``config``, ``in_channels``, ``learn_sigma``, ``y_embedder``, ``pos_embed``.

    ``c`` is ignored: diffusers embeds the timestep and class inside every block. A sampling call
    starts with one :meth:`condition_memory` call (that is how :func:`sample_dit` encodes the
    condition); the callbacks in ``on_call_start`` run there (a cache resets its state).
    """

    def __init__(self, transformer: nn.Module, config: DiTConfig):
        super().__init__()
        self.transformer = transformer
        self.config = config
        self.in_channels = config.in_channels
        self.learn_sigma = config.learn_sigma
        self.out_channels = config.in_channels * 2 if config.learn_sigma else config.in_channels
        self.on_call_start: list = []

    @classmethod
    def from_dit(cls, model: DiT) -> "DiffusersDiT":
        return cls(to_diffusers(model), model.config)

    @classmethod
    def from_transformer(cls, transformer: nn.Module) -> "DiffusersDiT":
        """Wrap a diffusers ``DiTTransformer2DModel`` (its :class:`DiTConfig` read from its config)."""
        c = transformer.config
        if c.norm_type != "ada_norm_zero" or c.num_embeds_ada_norm is None:
            raise ValueError(f"not a class-conditional DiT (norm_type {c.norm_type!r}, "
                             f"num_embeds_ada_norm {c.num_embeds_ada_norm})")
        out = c.out_channels or c.in_channels
        block = transformer.transformer_blocks[0]
        config = DiTConfig(input_size=c.sample_size, patch_size=c.patch_size, in_channels=c.in_channels,
                           hidden_size=c.num_attention_heads * c.attention_head_dim, depth=c.num_layers,
                           num_heads=c.num_attention_heads,
                           mlp_ratio=block.ff.net[0].proj.out_features / (c.num_attention_heads * c.attention_head_dim),
                           class_dropout_prob=block.norm1.emb.class_embedder.dropout_prob,
                           num_classes=c.num_embeds_ada_norm, learn_sigma=out == 2 * c.in_channels)
        return cls(transformer.eval(), config)

    @property
    def pos_embed(self) -> torch.Tensor:
        return self.transformer.pos_embed.pos_embed

    @property
    def y_embedder(self) -> nn.Module:
        """The class embedding (``num_classes``, ``embedding_table``) of block 0."""
        return self.transformer.transformer_blocks[0].norm1.emb.class_embedder

    def condition_memory(self, timesteps: Any, y: torch.Tensor) -> torch.Tensor:
        """Block 0's conditioning vector for all K timesteps, [B, K, 1, hidden] (informational: the
        forward recomputes it per block). Marks the start of a sampling call."""
        for callback in self.on_call_start:
            callback()
        emb = self.transformer.transformer_blocks[0].norm1.emb
        device = self.pos_embed.device
        t = torch.as_tensor(timesteps, device=device).reshape(-1)
        y = torch.as_tensor(y, device=device).reshape(-1)
        t_emb = emb.timestep_embedder(emb.time_proj(t).to(self.pos_embed.dtype))
        return (t_emb[None] + emb.class_embedder(y)[:, None]).unsqueeze(2)

    def forward(self, x: torch.Tensor, t: torch.Tensor, y: torch.Tensor,
                c: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.transformer(x, timestep=t, class_labels=y, return_dict=False)[0]


def load_diffusers_dit(path: Union[str, Path], map_location: Union[str, torch.device] = "cpu") -> DiffusersDiT:
    """A diffusers DiT from a local folder, never downloaded: a ``DiTPipeline`` folder
    (``model_index.json`` + ``transformer/``; its ``vae/``, if present, is recorded as
    ``model.vae_path``) or a ``DiTTransformer2DModel`` folder (``config.json`` + weights)."""
    from diffusers import DiTTransformer2DModel

    path = Path(path)
    folder = path / "transformer" if (path / "model_index.json").is_file() else path
    if not (folder / "config.json").is_file():
        raise FileNotFoundError(
            f"no diffusers DiT at {path}: expected a DiTPipeline folder (model_index.json, transformer/, vae/; "
            "e.g. facebook/DiT-XL-2-256 downloaded with huggingface-cli download --local-dir) or its "
            "transformer/ folder (config.json + diffusion_pytorch_model.safetensors)")
    cls_name = json.loads((folder / "config.json").read_text()).get("_class_name")
    if cls_name not in (None, "DiTTransformer2DModel", "Transformer2DModel"):
        raise ValueError(f"{folder} holds a {cls_name}, not a DiTTransformer2DModel")
    transformer = DiTTransformer2DModel.from_pretrained(str(folder), local_files_only=True, torch_dtype=torch.float32)
    model = DiffusersDiT.from_transformer(transformer).to(map_location)
    vae = path / "vae"
    model.vae_path = str(vae) if (vae / "config.json").is_file() else None
    model.checkpoint_info = {"source": str(folder), "format": "diffusers"}
    return model


def _adapt(model: Any) -> Optional[Target]:
    """:class:`DiffusersDiT`: the blocks of its diffusers transformer, its condition memory for a pruner."""
    from tts.engine import discover_sites

    if not isinstance(model, DiffusersDiT):
        return None
    return Target(denoiser=model, sites=discover_sites(model), supports_rollout=False,
                  condition=(model, "condition_memory"),
                  description=f"diffusers DiT ({type(model.transformer).__name__}, official calling convention)")


register_model_adapter("diffusers DiT, official calling convention", _adapt)


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
