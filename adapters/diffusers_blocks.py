"""diffusers ``BasicTransformerBlock`` (DiT ``ada_norm_zero``, PixArt ``ada_norm_single``, plain
``layer_norm``; with or without ``attn2``) and the image models/pipelines built from it.

Branches: ``attn1`` (self-attention, gated for adaLN), ``attn2`` (cross-attention, if present) and
``ff`` (gated for adaLN). For ``ada_norm_zero`` the block's ``norm1`` computes the whole adaLN
modulation; it is evaluated lazily, only if some branch of the block computes. diffusers is never
imported unless such a block is present.
"""
from __future__ import annotations

from typing import Any, Optional

import torch
import torch.nn as nn

from tts.flops import register_mac_rule
from tts.spec import BlockSpec, BranchSpec, Lazy, Target, register_block_family, register_model_adapter

__all__ = ["basic_block_spec"]

_SUPPORTED = ("ada_norm_zero", "ada_norm_single", "layer_norm")


def _is_diffusers(obj: Any, name: str) -> bool:
    return any(c.__name__ == name and c.__module__.startswith("diffusers") for c in type(obj).__mro__)


def _basic_forward(
    block: nn.Module,
    run,
    hidden_states: torch.Tensor,
    attention_mask: Optional[torch.Tensor] = None,
    encoder_hidden_states: Optional[torch.Tensor] = None,
    encoder_attention_mask: Optional[torch.Tensor] = None,
    timestep: Optional[torch.Tensor] = None,
    cross_attention_kwargs: Optional[dict] = None,
    class_labels: Optional[torch.Tensor] = None,
    added_cond_kwargs: Optional[dict] = None,
) -> torch.Tensor:
    kw = dict(cross_attention_kwargs or {})
    kw.pop("scale", None)
    if "gligen" in kw:
        raise NotImplementedError("tts: BasicTransformerBlock with GLIGEN inputs is not supported")
    nt = block.norm_type
    batch = hidden_states.shape[0]
    if nt == "ada_norm_zero":
        # (norm1(x) modulated, gate_msa, shift_mlp, scale_mlp, gate_mlp)
        mod = Lazy(lambda: block.norm1(hidden_states, timestep, class_labels, hidden_dtype=hidden_states.dtype))
    elif nt == "ada_norm_single":
        # (shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp), each [B, 1, D]
        mod = Lazy(lambda: (block.scale_shift_table[None] + timestep.reshape(batch, 6, -1)).chunk(6, dim=1))
    else:
        mod = None

    def self_attn(h, m, ehs, amask):
        if nt == "ada_norm_zero":
            nh = m[0]
        elif nt == "ada_norm_single":
            nh = block.norm1(h) * (1 + m[1]) + m[0]
        else:
            nh = block.norm1(h)
        out = block.attn1(nh, encoder_hidden_states=ehs if block.only_cross_attention else None,
                          attention_mask=amask, **kw)
        if nt == "ada_norm_zero":
            return m[1].unsqueeze(1) * out
        if nt == "ada_norm_single":
            return m[2] * out
        return out

    def cross_attn(h, ehs, emask):
        nh = h if nt == "ada_norm_single" else block.norm2(h)
        return block.attn2(nh, encoder_hidden_states=ehs, attention_mask=emask, **kw)

    def feed_forward(h, m):
        if nt == "ada_norm_zero":
            nh = block.norm3(h) * (1 + m[3][:, None]) + m[2][:, None]
        elif nt == "ada_norm_single":
            nh = block.norm2(h) * (1 + m[4]) + m[3]
        else:
            nh = block.norm3(h)
        if block._chunk_size is not None:
            from diffusers.models.attention import _chunked_feed_forward

            out = _chunked_feed_forward(block.ff, nh, block._chunk_dim, block._chunk_size)
        else:
            out = block.ff(nh)
        if nt == "ada_norm_zero":
            return m[4].unsqueeze(1) * out
        if nt == "ada_norm_single":
            return m[5] * out
        return out

    x = hidden_states
    x = run(0, self_attn, x, mod, encoder_hidden_states, attention_mask) + x
    i = 1
    if block.attn2 is not None:
        x = run(1, cross_attn, x, encoder_hidden_states, encoder_attention_mask) + x
        i = 2
    x = run(i, feed_forward, x, mod) + x
    return x


def basic_block_spec(block: nn.Module) -> BlockSpec:
    """The residual branches (attn1, attn2, ff) of a diffusers ``BasicTransformerBlock``."""
    nt = block.norm_type
    if nt not in _SUPPORTED:
        raise NotImplementedError(
            f"tts: BasicTransformerBlock with norm_type={nt!r} is not supported (supported: "
            f"{_SUPPORTED}); declare the block with a BlockSpec instead"
        )
    if block.pos_embed is not None:
        raise NotImplementedError("tts: BasicTransformerBlock with a per-block pos_embed is not supported")
    sa_mods = ("attn1",) + (("norm1",) if nt != "ada_norm_zero" else ())
    branches = [BranchSpec("attn1", "self_attn", sa_mods)]
    if block.attn2 is not None:
        branches.append(BranchSpec("attn2", "cross_attn", ("attn2",) + (("norm2",) if nt != "ada_norm_single" else ())))
    ff_norm = "norm2" if nt == "ada_norm_single" else "norm3"
    branches.append(BranchSpec("ff", "mlp", ("ff", ff_norm)))
    return BlockSpec("diffusers.BasicTransformerBlock", tuple(branches), _basic_forward)


def _match(module: nn.Module) -> Optional[BlockSpec]:
    if _is_diffusers(module, "BasicTransformerBlock"):
        return basic_block_spec(module)
    return None


def _attention_products(attn: nn.Module, args: tuple, kwargs: dict, out: Any) -> int:
    """QK^T and AV MACs of a diffusers ``Attention`` (its projections are counted as Linears)."""
    h = args[0] if args else kwargs["hidden_states"]
    ehs = kwargs.get("encoder_hidden_states", args[1] if len(args) > 1 else None)
    n = h.shape[1] if h.dim() == 3 else h.shape[2] * h.shape[3]
    s = n if ehs is None else ehs.shape[1]
    return h.shape[0] * n * s * (attn.inner_dim + attn.inner_kv_dim)


def _register_attention_rule() -> None:
    from diffusers.models.attention_processor import Attention

    register_mac_rule(Attention, _attention_products)


_IMAGE_MODELS = ("DiTTransformer2DModel", "PixArtTransformer2DModel")


def _adapt(model: Any) -> Optional[Target]:
    """diffusers DiT/PixArt transformers and pipelines: image generators, no rollout direction."""
    from tts.engine import discover_sites

    if hasattr(model, "transformer") and type(model).__name__.endswith("Pipeline") and _is_diffusers(model, "DiffusionPipeline"):
        model = model.transformer
    if not any(_is_diffusers(model, n) for n in _IMAGE_MODELS):
        return None
    _register_attention_rule()
    return Target(
        denoiser=model,
        sites=discover_sites(model),
        supports_rollout=False,
        description=f"diffusers {type(model).__name__}",
    )


def _match_and_register(module: nn.Module) -> Optional[BlockSpec]:
    spec = _match(module)
    if spec is not None:
        _register_attention_rule()
    return spec


register_block_family("diffusers.BasicTransformerBlock", _match_and_register)
register_model_adapter("diffusers image transformer / pipeline", _adapt)
