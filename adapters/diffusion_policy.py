"""Diffusion Policy's transformer ("DP-T", Chi et al. 2023) and its tts adapter.

:class:`TransformerForDiffusion` keeps the parameter names of diffusion_policy's
``model/diffusion/transformer_for_diffusion.py`` (``input_emb``, ``pos_emb``, ``cond_obs_emb``,
``cond_pos_emb``, ``encoder``, ``decoder.layers.N``, ``ln_f``, ``head``, ``_dummy_variable``), so an
official checkpoint's state dict loads unchanged. Written from the paper and that module's layout.

Prunable branches: the SA / CA / FFN of every decoder layer (3 per layer and step); the condition
encoder, embeddings, ``ln_f`` and ``head`` are never pruned. Two additions serve fast sampling:
:meth:`TransformerForDiffusion.condition_memory` encodes the condition for all K denoising steps in
one batched call (the obs tokens do not change across steps), and ``forward(..., memory=...)``
accepts that precomputed memory.

The adapter recognises the layout (attribute names and types), not these additions, so the official
class works unmodified: its own forward runs with the decoder layers' branches hooked, and a learned
pruner reads a condition memory that :func:`encode_condition` builds from the official attributes
(for that it needs the timesteps of a call: accelerate the policy, whose ``noise_scheduler`` has them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import torch
import torch.nn as nn

from tts.spec import Target, register_model_adapter

from .schedulers import FastDDPM
from .torch_layers import decoder_layer_spec, encoder_layer_spec

__all__ = ["DPTransformerConfig", "TransformerForDiffusion", "SinusoidalPosEmb", "encode_condition", "sample_actions"]


class SinusoidalPosEmb(nn.Module):
    """Diffusion Policy's timestep embedding: [sin | cos] of t times geometric frequencies."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        scale = math.log(10000) / (half - 1)
        freqs = torch.exp(torch.arange(half, device=x.device) * -scale)
        args = x[:, None] * freqs[None, :]
        return torch.cat((args.sin(), args.cos()), dim=-1)


@dataclass(frozen=True)
class DPTransformerConfig:
    """Arguments of Diffusion Policy's ``TransformerForDiffusion`` (same names and defaults)."""

    input_dim: int
    output_dim: int
    horizon: int
    n_obs_steps: Optional[int] = None
    cond_dim: int = 0
    n_layer: int = 12
    n_head: int = 12
    n_emb: int = 768
    p_drop_emb: float = 0.1
    p_drop_attn: float = 0.1
    causal_attn: bool = False
    time_as_cond: bool = True
    obs_as_cond: bool = False
    n_cond_layers: int = 0


def _additive(mask: torch.Tensor) -> torch.Tensor:
    return mask.float().masked_fill(~mask, float("-inf")).masked_fill(mask, 0.0)


class TransformerForDiffusion(nn.Module):
    """Noise predictor eps(x_t, t, obs) of DP-T, parameter-compatible with diffusion_policy."""

    def __init__(self, config: DPTransformerConfig):
        super().__init__()
        c = config
        self.config = c
        n_obs_steps = c.horizon if c.n_obs_steps is None else c.n_obs_steps
        T, T_cond = c.horizon, 1
        if not c.time_as_cond:
            T, T_cond = T + 1, 0
        obs_as_cond = c.cond_dim > 0
        if obs_as_cond:
            if not c.time_as_cond:
                raise ValueError("obs_as_cond requires time_as_cond")
            T_cond += n_obs_steps
        self._dummy_variable = nn.Parameter()
        self.input_emb = nn.Linear(c.input_dim, c.n_emb)
        self.pos_emb = nn.Parameter(torch.zeros(1, T, c.n_emb))
        self.drop = nn.Dropout(c.p_drop_emb)
        self.time_emb = SinusoidalPosEmb(c.n_emb)
        self.cond_obs_emb = nn.Linear(c.cond_dim, c.n_emb) if obs_as_cond else None
        self.cond_pos_emb = None
        self.encoder = None
        self.decoder = None

        def enc_layer():
            return nn.TransformerEncoderLayer(c.n_emb, c.n_head, 4 * c.n_emb, c.p_drop_attn,
                                              activation="gelu", batch_first=True, norm_first=True)

        self.encoder_only = T_cond == 0
        if not self.encoder_only:
            self.cond_pos_emb = nn.Parameter(torch.zeros(1, T_cond, c.n_emb))
            if c.n_cond_layers > 0:
                self.encoder = nn.TransformerEncoder(enc_layer(), c.n_cond_layers, enable_nested_tensor=False)
            else:
                self.encoder = nn.Sequential(nn.Linear(c.n_emb, 4 * c.n_emb), nn.Mish(), nn.Linear(4 * c.n_emb, c.n_emb))
            layer = nn.TransformerDecoderLayer(c.n_emb, c.n_head, 4 * c.n_emb, c.p_drop_attn,
                                               activation="gelu", batch_first=True, norm_first=True)
            self.decoder = nn.TransformerDecoder(layer, c.n_layer)
        else:
            self.encoder = nn.TransformerEncoder(enc_layer(), c.n_layer, enable_nested_tensor=False)

        if c.causal_attn:
            self.register_buffer("mask", _additive(torch.tril(torch.ones(T, T, dtype=torch.bool))))
            if c.time_as_cond and obs_as_cond:
                t, s = torch.meshgrid(torch.arange(T), torch.arange(T_cond), indexing="ij")
                # action token i sees cond token j iff i >= j - 1 (token 0 is the time token)
                self.register_buffer("memory_mask", _additive(t >= (s - 1)))
            else:
                self.memory_mask = None
        else:
            self.mask = None
            self.memory_mask = None
        self.ln_f = nn.LayerNorm(c.n_emb)
        self.head = nn.Linear(c.n_emb, c.output_dim)
        self.T, self.T_cond, self.horizon = T, T_cond, c.horizon
        self.obs_as_cond = obs_as_cond
        self.apply(self._init_weights)

    def _init_weights(self, module: nn.Module) -> None:
        """Diffusion Policy's initialisation (normal 0.02 weights, zero biases, unit LayerNorm)."""
        if isinstance(module, (nn.Linear, nn.Embedding)):
            nn.init.normal_(module.weight, mean=0.0, std=0.02)
            if isinstance(module, nn.Linear) and module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.MultiheadAttention):
            for name in ("in_proj_weight", "q_proj_weight", "k_proj_weight", "v_proj_weight"):
                if getattr(module, name) is not None:
                    nn.init.normal_(getattr(module, name), mean=0.0, std=0.02)
            for name in ("in_proj_bias", "bias_k", "bias_v"):
                if getattr(module, name) is not None:
                    nn.init.zeros_(getattr(module, name))
        elif isinstance(module, nn.LayerNorm):
            nn.init.zeros_(module.bias)
            nn.init.ones_(module.weight)
        elif isinstance(module, TransformerForDiffusion):
            nn.init.normal_(module.pos_emb, mean=0.0, std=0.02)
            if module.cond_obs_emb is not None:
                nn.init.normal_(module.cond_pos_emb, mean=0.0, std=0.02)

    # ------------------------------------------------------------------ condition encoder
    def _encode(self, tokens: torch.Tensor) -> torch.Tensor:
        tc = tokens.shape[-2]
        return self.encoder(self.drop(tokens + self.cond_pos_emb[:, :tc, :]))

    def condition_memory(self, timesteps: torch.Tensor, cond: Optional[torch.Tensor]) -> torch.Tensor:
        """Encoder output for all K timesteps at once: [B, K, T_cond, n_emb] (one batched call)."""
        if self.encoder_only:
            raise ValueError("encoder-only (BERT) DP transformers have no condition memory")
        return encode_condition(self, timesteps, cond)

    # ------------------------------------------------------------------ forward
    def forward(self, sample: torch.Tensor, timestep: Any, cond: Optional[torch.Tensor] = None,
                memory: Optional[torch.Tensor] = None, **kwargs) -> torch.Tensor:
        """sample [B, T, input_dim], timestep scalar or [B], cond [B, To, cond_dim] -> [B, T, output_dim].

        ``memory`` ([B, T_cond, n_emb]) skips the condition encoder (see :meth:`condition_memory`).
        """
        x_in = self.input_emb(sample)
        if self.encoder_only or memory is None:
            t = timestep
            if not torch.is_tensor(t):
                t = torch.tensor([t], dtype=torch.long, device=sample.device)
            elif t.dim() == 0:
                t = t[None].to(sample.device)
            time = self.time_emb(t.expand(sample.shape[0])).unsqueeze(1)
        if self.encoder_only:
            tokens = torch.cat([time, x_in], dim=1)
            x = self.drop(tokens + self.pos_emb[:, : tokens.shape[1], :])
            x = self.encoder(src=x, mask=self.mask)[:, 1:, :]
        else:
            if memory is None:
                tokens = time
                if self.obs_as_cond:
                    tokens = torch.cat([tokens, self.cond_obs_emb(cond)], dim=1)
                memory = self._encode(tokens)
            x = self.drop(x_in + self.pos_emb[:, : x_in.shape[1], :])
            x = self.decoder(tgt=x, memory=memory, tgt_mask=self.mask, memory_mask=self.memory_mask)
        return self.head(self.ln_f(x))


CONDITION_ATTRIBUTES = ("time_emb", "cond_obs_emb", "cond_pos_emb", "drop", "encoder")


_TOKENWISE = (nn.Linear, nn.Mish, nn.GELU, nn.ReLU, nn.SiLU, nn.Tanh, nn.Identity, nn.Dropout)


def _tokenwise(encoder: nn.Module) -> bool:
    """Whether the condition encoder maps every token independently (DP's ``n_cond_layers = 0`` MLP)."""
    return isinstance(encoder, nn.Sequential) and all(isinstance(m, _TOKENWISE) for m in encoder)


def encode_condition(model: nn.Module, timesteps: Any, cond: Optional[torch.Tensor],
                     batch: Optional[int] = None) -> torch.Tensor:
    """The condition memory of a DP transformer for all K ``timesteps`` of a call, [B, K, T_cond,
    n_emb], in one batched encoder call, from the official attributes only (``time_emb``,
    ``cond_obs_emb`` (None without observation tokens), ``cond_pos_emb``, ``drop``, ``encoder``): what
    the official forward computes as ``memory`` at each step. ``batch`` expands a memory without
    observation tokens to the batch."""
    timesteps = torch.as_tensor(timesteps).reshape(-1)
    K = timesteps.shape[0]
    B = cond.shape[0] if cond is not None else (batch or 1)
    time = model.time_emb(timesteps.to(model.pos_emb.device))  # [K, D]
    if _tokenwise(model.encoder) and not (model.drop.training and model.drop.p > 0):
        # an MLP encoder (n_cond_layers = 0) maps each token alone: the time token once per step and
        # the observation tokens once per call, instead of every token at every step (B*K*Tc rows)
        pos = model.cond_pos_emb
        time_out = model.encoder(model.drop(time + pos[0, :1, :]))  # [K, D]
        parts = [time_out[None, :, None, :].expand(B, K, 1, -1)]
        if model.cond_obs_emb is not None:
            obs = model.cond_obs_emb(cond)  # [B, To, D]
            obs_out = model.encoder(model.drop(obs + pos[:, 1:1 + obs.shape[1], :]))
            parts.append(obs_out[:, None].expand(B, K, -1, -1))
        return torch.cat(parts, dim=2)
    tokens = time[None, :, None, :].expand(B, K, 1, -1)
    if model.cond_obs_emb is not None:
        obs = model.cond_obs_emb(cond)  # [B, To, D]
        tokens = torch.cat([tokens, obs[:, None].expand(B, K, -1, -1)], dim=2)
    tc = tokens.shape[2]
    out = model.encoder(model.drop(tokens.reshape(B * K, tc, -1) + model.cond_pos_emb[:, :tc, :]))
    return out.reshape(B, K, out.shape[1], out.shape[2])


@torch.no_grad()
def sample_actions(model: TransformerForDiffusion, cond: Optional[torch.Tensor], scheduler: Any, *,
                   batch: Optional[int] = None, generator: Optional[torch.Generator] = None,
                   fast: bool = True) -> torch.Tensor:
    """Diffusion Policy's conditional sampling loop (normalised actions [B, horizon, output_dim]).

    ``scheduler`` is a diffusers scheduler with ``set_timesteps`` already called. ``fast=True``
    encodes the condition once per call and uses precomputed DDPM coefficients (:class:`FastDDPM`,
    DDPM only); ``fast=False`` is DP's stock loop (encoder and ``scheduler.step`` every step).
    """
    p = next(model.parameters())
    B = cond.shape[0] if cond is not None else (batch or 1)
    x = torch.randn(B, model.horizon, model.config.input_dim, generator=generator, device=p.device, dtype=p.dtype)
    if not fast:
        for t in scheduler.timesteps:
            out = model(x, t, cond)
            x = scheduler.step(out, t, x, generator=generator).prev_sample
        return x
    stepper = FastDDPM(scheduler)
    memory = model.condition_memory(stepper.timesteps, cond)
    for i, t in enumerate(stepper.timesteps):
        out = model(x, t, cond, memory=memory[:, i])
        x = stepper.step(i, out, x, generator)
    return x


def is_dp_transformer(model: Any) -> bool:
    """Diffusion Policy's ``TransformerForDiffusion`` layout (ours or the official class), by its
    attribute names and types: embeddings, ``ln_f``/``head``, and a decoder of
    ``nn.TransformerDecoder`` or, in the encoder-only (BERT) mode, an ``nn.TransformerEncoder``."""
    if not isinstance(model, nn.Module):
        return False
    typed = (("input_emb", nn.Linear), ("head", nn.Linear), ("ln_f", nn.Module), ("time_emb", nn.Module),
             ("pos_emb", torch.Tensor))
    if not all(isinstance(getattr(model, name, None), cls) for name, cls in typed):
        return False
    decoder, encoder = getattr(model, "decoder", None), getattr(model, "encoder", None)
    return isinstance(decoder, nn.TransformerDecoder) or (decoder is None and isinstance(encoder, nn.TransformerEncoder))


def has_condition_encoder(model: nn.Module) -> bool:
    """Whether :func:`encode_condition` applies (a decoder model with the official condition attributes)."""
    return (isinstance(getattr(model, "decoder", None), nn.TransformerDecoder)
            and all(hasattr(model, a) for a in CONDITION_ATTRIBUTES)
            and isinstance(model.cond_pos_emb, torch.Tensor) and isinstance(model.encoder, nn.Module))


def _skip_blocks(model: nn.Module):
    """``Target.skip_blocks`` of a decoder DP transformer, from the official attributes: the forward
    with the decoder layers replaced by ``+ delta`` (condition encoder and time embedding unused).
    The position embedding plus ``delta`` is kept between steps that reuse the same sum."""
    memo: dict = {}

    def skip(args: tuple, kwargs: dict, delta: torch.Tensor) -> torch.Tensor:
        sample = kwargs["sample"] if "sample" in kwargs else args[0]
        n = sample.shape[1]
        if model.drop.training and model.drop.p > 0:  # dropout between the embedding and the blocks
            x = model.drop(model.input_emb(sample) + model.pos_emb[:, :n, :]) + delta
        else:
            hit = memo.get("pos")
            if hit is None or hit[0] is not delta or hit[1] != n:
                memo["pos"] = hit = (delta, n, model.pos_emb[:, :n, :] + delta)
            x = model.input_emb(sample) + hit[2]
        norm = model.decoder.norm
        if norm is not None:
            x = norm(x)
        return model.head(model.ln_f(x))

    return skip


def _adapt(model: Any) -> Optional[Target]:
    """A DP transformer: its decoder layers (or BERT-mode encoder layers) are the branch sites."""
    if not is_dp_transformer(model):
        return None
    if isinstance(model.decoder, nn.TransformerDecoder):
        sites = [(f"decoder.layers.{i}", m, decoder_layer_spec(m)) for i, m in enumerate(model.decoder.layers)]
        chain = True  # nn.TransformerDecoder: `for mod in layers: output = mod(output, memory, ...)`
    else:
        sites = [(f"encoder.layers.{i}", m, encoder_layer_spec(m)) for i, m in enumerate(model.encoder.layers)]
        chain = False
    target = Target(denoiser=model, sites=sites, description="Diffusion Policy transformer", chain=chain,
                    skip_blocks=_skip_blocks(model) if chain else None)
    if callable(getattr(model, "condition_memory", None)):
        target.condition = (model, "condition_memory")
    elif not has_condition_encoder(model):
        target.condition_note = ("an encoder-only Diffusion Policy transformer has no condition memory for a "
                                 "pruner to read")
    else:
        target.condition_note = (
            f"{type(model).__name__} has no condition_memory(timesteps, cond) method, and the module alone does "
            "not know the timesteps of a sampling call. Accelerate the policy (tts.accelerate(policy, ...)): its "
            "noise_scheduler gives them, and tts builds the memory from the official attributes "
            f"{', '.join(CONDITION_ATTRIBUTES)}"
        )
    return target


register_model_adapter("Diffusion Policy transformer", _adapt)
