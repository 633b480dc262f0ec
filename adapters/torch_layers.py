"""PyTorch's own ``nn.TransformerDecoderLayer`` / ``nn.TransformerEncoderLayer`` (pre- and post-norm).

Branches are exactly the layer's ``_sa_block``, ``_mha_block`` and ``_ff_block``. For post-norm
layers the norm after each residual add is not part of the branch (a reused branch still goes
through it). Per-sample key-padding masks are row-selected with the batch; 3-D attention masks
([batch*heads, L, S]) are not supported with per-sample decisions.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn
import torch.nn.functional as F

from tts.spec import BlockSpec, BranchSpec, register_block_family

__all__ = ["decoder_layer_spec", "encoder_layer_spec"]


def _kpm_batched(kpm: Optional[torch.Tensor], batch_dim: int) -> Optional[torch.Tensor]:
    """Key-padding masks are [B, S]; put their batch axis where the activations have it."""
    return kpm if kpm is None or batch_dim == 0 else kpm.t()


def _kpm_back(kpm: Optional[torch.Tensor], batch_dim: int) -> Optional[torch.Tensor]:
    return kpm if kpm is None or batch_dim == 0 else kpm.t()


def _decoder_forward(
    layer: nn.TransformerDecoderLayer,
    run,
    tgt: torch.Tensor,
    memory: torch.Tensor,
    tgt_mask: Optional[torch.Tensor] = None,
    memory_mask: Optional[torch.Tensor] = None,
    tgt_key_padding_mask: Optional[torch.Tensor] = None,
    memory_key_padding_mask: Optional[torch.Tensor] = None,
    tgt_is_causal: bool = False,
    memory_is_causal: bool = False,
) -> torch.Tensor:
    bd = 0 if layer.self_attn.batch_first else 1
    tkpm = _kpm_batched(tgt_key_padding_mask, bd)
    mkpm = _kpm_batched(memory_key_padding_mask, bd)

    def sa(h, kpm):
        return layer._sa_block(h, tgt_mask, _kpm_back(kpm, bd), tgt_is_causal)

    def ca(h, mem, kpm):
        return layer._mha_block(h, mem, memory_mask, _kpm_back(kpm, bd), memory_is_causal)

    x = tgt
    if layer.norm_first:
        x = x + run(0, lambda h, k: sa(layer.norm1(h), k), x, tkpm)
        x = x + run(1, lambda h, m, k: ca(layer.norm2(h), m, k), x, memory, mkpm)
        x = x + run(2, lambda h: layer._ff_block(layer.norm3(h)), x)
    else:
        x = layer.norm1(x + run(0, sa, x, tkpm))
        x = layer.norm2(x + run(1, ca, x, memory, mkpm))
        x = layer.norm3(x + run(2, layer._ff_block, x))
    return x


def _encoder_forward(
    layer: nn.TransformerEncoderLayer,
    run,
    src: torch.Tensor,
    src_mask: Optional[torch.Tensor] = None,
    src_key_padding_mask: Optional[torch.Tensor] = None,
    is_causal: bool = False,
) -> torch.Tensor:
    # same mask canonicalisation as the layer's own forward (bool masks become float)
    src_key_padding_mask = F._canonical_mask(
        mask=src_key_padding_mask,
        mask_name="src_key_padding_mask",
        other_type=F._none_or_dtype(src_mask),
        other_name="src_mask",
        target_type=src.dtype,
    )
    src_mask = F._canonical_mask(
        mask=src_mask, mask_name="src_mask", other_type=None, other_name="",
        target_type=src.dtype, check_other=False,
    )
    bd = 0 if layer.self_attn.batch_first else 1
    kpm = _kpm_batched(src_key_padding_mask, bd)

    def sa(h, k):
        return layer._sa_block(h, src_mask, _kpm_back(k, bd), is_causal=is_causal)

    x = src
    if layer.norm_first:
        x = x + run(0, lambda h, k: sa(layer.norm1(h), k), x, kpm)
        x = x + run(1, lambda h: layer._ff_block(layer.norm2(h)), x)
    else:
        x = layer.norm1(x + run(0, sa, x, kpm))
        x = layer.norm2(x + run(1, layer._ff_block, x))
    return x


_FF = ("linear1", "linear2", "dropout", "dropout3")


def decoder_layer_spec(layer: nn.TransformerDecoderLayer) -> BlockSpec:
    """The residual branches (self_attn, cross_attn, ff) of an ``nn.TransformerDecoderLayer``, pre- or post-norm."""
    pre = layer.norm_first
    return BlockSpec(
        family="torch.nn.TransformerDecoderLayer",
        branches=(
            BranchSpec("self_attn", "self_attn", ("self_attn", "dropout1") + (("norm1",) if pre else ())),
            BranchSpec("cross_attn", "cross_attn", ("multihead_attn", "dropout2") + (("norm2",) if pre else ())),
            BranchSpec("ff", "mlp", _FF + (("norm3",) if pre else ())),
        ),
        forward=_decoder_forward,
        batch_dim=0 if layer.self_attn.batch_first else 1,
        residual=pre,
    )


def encoder_layer_spec(layer: nn.TransformerEncoderLayer) -> BlockSpec:
    """The residual branches (self_attn, ff) of an ``nn.TransformerEncoderLayer``, pre- or post-norm."""
    pre = layer.norm_first
    return BlockSpec(
        family="torch.nn.TransformerEncoderLayer",
        branches=(
            BranchSpec("self_attn", "self_attn", ("self_attn", "dropout1") + (("norm1",) if pre else ())),
            BranchSpec("ff", "mlp", ("linear1", "linear2", "dropout", "dropout2") + (("norm2",) if pre else ())),
        ),
        forward=_encoder_forward,
        batch_dim=0 if layer.self_attn.batch_first else 1,
        residual=pre,
    )


def _match(module: nn.Module) -> Optional[BlockSpec]:
    if isinstance(module, nn.TransformerDecoderLayer):
        return decoder_layer_spec(module)
    if isinstance(module, nn.TransformerEncoderLayer):
        return encoder_layer_spec(module)
    return None


register_block_family("torch.nn.Transformer{Encoder,Decoder}Layer", _match)
