"""A DiT as a diffusers ``DiTTransformer2DModel``, and diffusers DiT folders as tts backbones.

This module

- converts an official-layout :class:`~tts.adapters.dit.DiT` into a diffusers
  ``DiTTransformer2DModel`` with the same function (:func:`to_diffusers`; float round-off only: the
  timestep features are switched to the official frequencies, see there),
- wraps it with the official calling convention (:class:`DiffusersDiT`), so
  :func:`~tts.adapters.dit.sample_dit` samples it with the same noise, scheduler and batched CFG as
  every tts method, and
- loads a diffusers DiT from a local folder (a ``DiTPipeline`` folder such as facebook/DiT-XL-2-256,
  or its ``transformer`` folder) as a :class:`DiffusersDiT` (:func:`load_diffusers_dit`; what
  :func:`~tts.adapters.dit.load_dit` does for a directory), which ``tts.accelerate`` and
  :func:`~tts.adapters.dit.sample_dit` take like an official-layout DiT (batched CFG [cond; uncond],
  condition memory for a pruner).

diffusers' own caches on such a model (baselines) live with the image evaluation suite.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Union

import torch
import torch.nn as nn

from tts.adapters.dit import DiT, DiTConfig
from tts.spec import Target, register_model_adapter

__all__ = ["to_diffusers", "DiffusersDiT", "load_diffusers_dit"]

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
        """The same weights as a diffusers ``DiTTransformer2DModel``, wrapped."""
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
        """The fixed 2-D position embedding."""
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
