"""DiT (Peebles & Xie 2023) in the layout of the official facebookresearch/DiT code, built on timm's
``Attention`` / ``Mlp`` with adaLN-Zero modulation, and its tts block family.

Parameter names follow the official ``models.py`` so that an official checkpoint's state dict
(e.g. ``DiT-XL-2-256x256.pt``) loads unchanged. Written from the paper and the checkpoint layout.

Branches of a DiT block (official forward ``x + gate * f(modulate(norm(x), shift, scale))``):
``attn`` (gated self-attention) and ``mlp`` (gated MLP). ``adaLN_modulation(c)`` is shared by both
and evaluated only if one of them computes. Any block with the attributes ``norm1, attn, norm2, mlp,
adaLN_modulation`` where ``attn``/``mlp`` are timm's ``Attention``/``Mlp`` is recognised, so users'
own copies of the DiT file work too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import torch
import torch.nn as nn

from tts.flops import register_mac_rule
from tts.spec import BlockSpec, BranchSpec, Lazy, Target, register_block_family, register_model_adapter

__all__ = ["DiTConfig", "DiT", "DiTBlock", "DIT_CONFIGS", "dit_block_spec"]


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


@dataclass(frozen=True)
class DiTConfig:
    input_size: int = 32
    patch_size: int = 2
    in_channels: int = 4
    hidden_size: int = 1152
    depth: int = 28
    num_heads: int = 16
    mlp_ratio: float = 4.0
    class_dropout_prob: float = 0.1
    num_classes: int = 1000
    learn_sigma: bool = True


DIT_CONFIGS = {
    "DiT-XL/2": DiTConfig(depth=28, hidden_size=1152, patch_size=2, num_heads=16),
    "DiT-L/2": DiTConfig(depth=24, hidden_size=1024, patch_size=2, num_heads=16),
    "DiT-B/2": DiTConfig(depth=12, hidden_size=768, patch_size=2, num_heads=12),
    "DiT-S/2": DiTConfig(depth=12, hidden_size=384, patch_size=2, num_heads=6),
}


class TimestepEmbedder(nn.Module):
    """Sinusoidal features of t (cos first, as in the official code) followed by a 2-layer MLP."""

    def __init__(self, hidden_size: int, frequency_embedding_size: int = 256):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(frequency_embedding_size, hidden_size, bias=True),
            nn.SiLU(),
            nn.Linear(hidden_size, hidden_size, bias=True),
        )
        self.frequency_embedding_size = frequency_embedding_size

    @staticmethod
    def timestep_embedding(t: torch.Tensor, dim: int, max_period: int = 10000) -> torch.Tensor:
        half = dim // 2
        freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
        args = t[:, None].float() * freqs[None]
        emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
        if dim % 2:
            emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
        return emb

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.timestep_embedding(t, self.frequency_embedding_size))


class LabelEmbedder(nn.Module):
    """Class embedding with an extra "null" class used for classifier-free guidance dropout."""

    def __init__(self, num_classes: int, hidden_size: int, dropout_prob: float):
        super().__init__()
        use_cfg_embedding = dropout_prob > 0
        self.embedding_table = nn.Embedding(num_classes + use_cfg_embedding, hidden_size)
        self.num_classes = num_classes
        self.dropout_prob = dropout_prob

    def forward(self, labels: torch.Tensor, train: bool, force_drop_ids: Optional[torch.Tensor] = None) -> torch.Tensor:
        if (train and self.dropout_prob > 0) or force_drop_ids is not None:
            if force_drop_ids is None:
                drop = torch.rand(labels.shape[0], device=labels.device) < self.dropout_prob
            else:
                drop = force_drop_ids == 1
            labels = torch.where(drop, self.num_classes, labels)
        return self.embedding_table(labels)


class DiTBlock(nn.Module):
    def __init__(self, hidden_size: int, num_heads: int, mlp_ratio: float = 4.0):
        super().__init__()
        from timm.layers import Attention, Mlp

        self.norm1 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(hidden_size, num_heads=num_heads, qkv_bias=True)
        self.norm2 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(in_features=hidden_size, hidden_features=int(hidden_size * mlp_ratio),
                       act_layer=lambda: nn.GELU(approximate="tanh"), drop=0)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 6 * hidden_size, bias=True))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp = self.adaLN_modulation(c).chunk(6, dim=1)
        x = x + gate_msa.unsqueeze(1) * self.attn(modulate(self.norm1(x), shift_msa, scale_msa))
        x = x + gate_mlp.unsqueeze(1) * self.mlp(modulate(self.norm2(x), shift_mlp, scale_mlp))
        return x


class FinalLayer(nn.Module):
    def __init__(self, hidden_size: int, patch_size: int, out_channels: int):
        super().__init__()
        self.norm_final = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.linear = nn.Linear(hidden_size, patch_size * patch_size * out_channels, bias=True)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 2 * hidden_size, bias=True))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift, scale = self.adaLN_modulation(c).chunk(2, dim=1)
        return self.linear(modulate(self.norm_final(x), shift, scale))


def sincos_pos_embed_2d(dim: int, grid: int) -> torch.Tensor:
    """Fixed 2-D sin-cos position embedding [grid*grid, dim] (half the channels per axis)."""
    coords = torch.arange(grid, dtype=torch.float64)
    gy, gx = torch.meshgrid(coords, coords, indexing="ij")

    def axis(pos: torch.Tensor, d: int) -> torch.Tensor:
        omega = 1.0 / 10000 ** (torch.arange(d // 2, dtype=torch.float64) / (d / 2.0))
        out = pos.reshape(-1)[:, None] * omega[None]
        return torch.cat([torch.sin(out), torch.cos(out)], dim=1)

    # the official code embeds the w-coordinate grid first
    return torch.cat([axis(gx, dim // 2), axis(gy, dim // 2)], dim=1).float()


class DiT(nn.Module):
    """Class-conditional DiT with the official module/parameter names."""

    def __init__(self, config: DiTConfig = DiTConfig()):
        super().__init__()
        from timm.layers import PatchEmbed

        self.config = config
        self.learn_sigma = config.learn_sigma
        self.in_channels = config.in_channels
        self.out_channels = config.in_channels * 2 if config.learn_sigma else config.in_channels
        self.patch_size = config.patch_size
        self.num_heads = config.num_heads
        h = config.hidden_size
        self.x_embedder = PatchEmbed(config.input_size, config.patch_size, config.in_channels, h, bias=True)
        self.t_embedder = TimestepEmbedder(h)
        self.y_embedder = LabelEmbedder(config.num_classes, h, config.class_dropout_prob)
        num_patches = self.x_embedder.num_patches
        self.pos_embed = nn.Parameter(torch.zeros(1, num_patches, h), requires_grad=False)
        self.blocks = nn.ModuleList([DiTBlock(h, config.num_heads, config.mlp_ratio) for _ in range(config.depth)])
        self.final_layer = FinalLayer(h, config.patch_size, self.out_channels)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """DiT's initialisation: xavier linears, fixed sin-cos positions, zeroed adaLN outputs."""

        def basic(m: nn.Module) -> None:
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

        self.apply(basic)
        grid = int(self.x_embedder.num_patches ** 0.5)
        self.pos_embed.data.copy_(sincos_pos_embed_2d(self.pos_embed.shape[-1], grid).unsqueeze(0))
        w = self.x_embedder.proj.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        nn.init.zeros_(self.x_embedder.proj.bias)
        nn.init.normal_(self.y_embedder.embedding_table.weight, std=0.02)
        nn.init.normal_(self.t_embedder.mlp[0].weight, std=0.02)
        nn.init.normal_(self.t_embedder.mlp[2].weight, std=0.02)
        for block in self.blocks:
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
        for layer in (self.final_layer.adaLN_modulation[-1], self.final_layer.linear):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def unpatchify(self, x: torch.Tensor) -> torch.Tensor:
        c, p = self.out_channels, self.patch_size
        h = w = int(x.shape[1] ** 0.5)
        x = x.reshape(x.shape[0], h, w, p, p, c)
        x = torch.einsum("nhwpqc->nchpwq", x)
        return x.reshape(x.shape[0], c, h * p, w * p)

    def forward(self, x: torch.Tensor, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        x = self.x_embedder(x) + self.pos_embed
        c = self.t_embedder(t) + self.y_embedder(y, self.training)
        for block in self.blocks:
            x = block(x, c)
        return self.unpatchify(self.final_layer(x, c))

    def forward_with_cfg(self, x: torch.Tensor, t: torch.Tensor, y: torch.Tensor, cfg_scale: float) -> torch.Tensor:
        """Batched classifier-free guidance: x holds [cond; uncond] halves with identical latents."""
        half = x[: len(x) // 2]
        out = self.forward(torch.cat([half, half], dim=0), t, y)
        eps, rest = out[:, : self.in_channels], out[:, self.in_channels:]
        cond, uncond = torch.split(eps, len(eps) // 2, dim=0)
        half_eps = uncond + cfg_scale * (cond - uncond)
        return torch.cat([torch.cat([half_eps, half_eps], dim=0), rest], dim=1)


# ---------------------------------------------------------------------------------- tts family
def _dit_block_forward(block: nn.Module, run, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    mod = Lazy(lambda: block.adaLN_modulation(c).chunk(6, dim=1))

    def attn(h, m):
        return m[2].unsqueeze(1) * block.attn(modulate(block.norm1(h), m[0], m[1]))

    def mlp(h, m):
        return m[5].unsqueeze(1) * block.mlp(modulate(block.norm2(h), m[3], m[4]))

    x = x + run(0, attn, x, mod)
    x = x + run(1, mlp, x, mod)
    return x


def dit_block_spec(block: nn.Module) -> BlockSpec:
    return BlockSpec(
        family="DiT block (timm Attention/Mlp + adaLN)",
        branches=(BranchSpec("attn", "self_attn", ("attn", "norm1")), BranchSpec("mlp", "mlp", ("mlp", "norm2"))),
        forward=_dit_block_forward,
    )


def _class_names(obj: Any) -> set[str]:
    return {f"{c.__module__.split('.')[0]}.{c.__name__}" for c in type(obj).__mro__}


def _match(module: nn.Module) -> Optional[BlockSpec]:
    if not all(hasattr(module, a) for a in ("norm1", "attn", "norm2", "mlp", "adaLN_modulation")):
        return None
    if "timm.Attention" in _class_names(module.attn) and "timm.Mlp" in _class_names(module.mlp):
        _register_attention_rule()
        return dit_block_spec(module)
    return None


def _attention_products(attn: nn.Module, args: tuple, kwargs: dict, out: Any) -> int:
    """QK^T and AV MACs of timm's ``Attention`` (qkv/proj are counted as Linears)."""
    x = args[0] if args else kwargs["x"]
    b, n = x.shape[0], x.shape[1]
    return 2 * b * n * n * attn.num_heads * attn.head_dim


def _register_attention_rule() -> None:
    from timm.layers import Attention

    register_mac_rule(Attention, _attention_products)


def _adapt(model: Any) -> Optional[Target]:
    """Official-layout DiT models: image generators, no rollout direction."""
    from tts.engine import discover_sites

    names = ("x_embedder", "t_embedder", "y_embedder", "blocks", "final_layer")
    if not (isinstance(model, nn.Module) and all(hasattr(model, n) for n in names)):
        return None
    return Target(denoiser=model, sites=discover_sites(model), supports_rollout=False,
                  description=f"DiT ({type(model).__name__})")


register_block_family("DiT block (timm Attention/Mlp + adaLN)", _match)
register_model_adapter("official-layout DiT", _adapt)
