"""DiT sampling for the image evaluation: per-index noise, process shards, VAE decoding, the
accelerator of a method of the vocabulary (eval/common/methods.py) and its decision / MACs counts."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

import tts
from common.methods import Method, install
from tts.adapters.dit import DiT

from .diffusers_cache import DiffusersCache, calibrate_fbc_threshold

__all__ = ["shard", "index_seed", "sample_noise", "to_uint8_rgb", "load_vae", "build_accelerator", "sampler_of",
           "describe", "last_call_counts", "mlp_share", "resolve_budget", "Meter", "dense_macs_per_image",
           "CALIBRATION_IMAGES", "SD_VAE_SCALE"]

CALIBRATION_IMAGES = 32
SD_VAE_SCALE = 0.18215  # latent scale of the Stable Diffusion VAE that DiT was trained with


def shard(num_samples: int, num_processes: int, rank: int) -> range:
    """The contiguous block of sample indices of process ``rank`` (sizes differ by at most one)."""
    return range(rank * num_samples // num_processes, (rank + 1) * num_samples // num_processes)


def index_seed(seed: int, index: int) -> int:
    """Seed of sample ``index``'s initial noise: a hash of (seed, index), independent of the process count."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1, np.uint64)[0])


def sample_noise(seed: int, indices: Sequence[int], shape: tuple[int, ...]) -> torch.Tensor:
    """Initial noise [len(indices), *shape], each row from its own (seed, index) generator."""
    return torch.stack([torch.randn(shape, generator=torch.Generator().manual_seed(index_seed(seed, i)))
                        for i in indices])


def to_uint8_rgb(images: torch.Tensor) -> torch.Tensor:
    """Model-space images [B, C, H, W] in [-1, 1] (C = 1 or 3) -> uint8 RGB [B, H, W, 3]."""
    if images.dim() != 4 or images.shape[1] not in (1, 3):
        raise ValueError(f"expected images [B, 1 or 3, H, W] in [-1, 1], got {tuple(images.shape)} "
                         "(a latent model needs --vae to decode its samples)")
    x = ((images.float() + 1.0) * 127.5).round().clamp(0, 255).to(torch.uint8)
    if x.shape[1] == 1:
        x = x.expand(-1, 3, -1, -1)
    return x.permute(0, 2, 3, 1).contiguous().cpu()


def load_vae(path: str, device: torch.device):
    """A diffusers AutoencoderKL from a local folder (never downloaded)."""
    from diffusers import AutoencoderKL

    p = Path(path)
    if not (p / "config.json").is_file():
        raise FileNotFoundError(
            f"no diffusers VAE at {p}: download stabilityai/sd-vae-ft-ema (or sd-vae-ft-mse) as a diffusers "
            "folder (config.json + diffusion_pytorch_model.safetensors) and pass --vae FOLDER")
    return AutoencoderKL.from_pretrained(str(p), local_files_only=True).to(device).eval()


def is_diffusers_cache(acc: Any) -> bool:
    return isinstance(acc, DiffusersCache)


def sampler_steps(method: Method, steps: int, scheduler: str) -> tuple[int, str]:
    """The (steps, scheduler) ``method`` samples with: a fewer-step sampler's own (``ddim:K``), an
    engine method's base (``SPEC+ddim:K``), else the suite's ``steps`` and ``scheduler``."""
    if method.sampler is not None:
        return method.sampler.steps, method.sampler.scheduler
    return steps, scheduler


def sampler_of(model: DiT, acc: Any):
    """The module to sample: the converted copy for a diffusers cache, else ``model``."""
    return acc.model if is_diffusers_cache(acc) else model


def describe(acc: Any) -> str:
    return acc.describe() if is_diffusers_cache(acc) else acc.plan.describe()


def last_call_counts(acc: Any) -> dict[str, float]:
    """decisions, reused, macs_dense, macs_realised, macs_pruner of ``acc``'s last sampling call."""
    if is_diffusers_cache(acc):
        call = acc.last_call()
        decisions = 2 * acc.depth * call.forwards
        return dict(decisions=decisions, reused=decisions - call.computed,
                    macs_dense=call.macs_dense(), macs_realised=call.macs, macs_pruner=0.0)
    summary = acc.summary()
    call = summary.calls[-1]
    d = call.decisions()
    dense, realised = summary.macs(call)
    return dict(decisions=d.numel(), reused=int((d != tts.plans.COMPUTE).sum()), macs_dense=dense,
                macs_realised=realised, macs_pruner=call.pruner_macs)


def mlp_share(model: DiT) -> float:
    """Share of a DiT block's branch MACs in its MLP (the token-wise branch): per token the MLP costs
    2 * D * mlp_hidden, attention 4 * D^2 (qkv, proj) + 2 * N * D (scores, weighted sum)."""
    cfg = model.config
    D, N = cfg.hidden_size, (cfg.input_size // cfg.patch_size) ** 2
    mlp = 2 * D * int(D * cfg.mlp_ratio)
    return mlp / (mlp + 4 * D * D + 2 * N * D)


class Meter:
    """Per-process totals of decisions and MACs over the sampling calls of an accelerator."""

    def __init__(self) -> None:
        self.images = 0
        self.calls = 0
        self.decisions = 0
        self.reused = 0
        self.macs_dense = 0.0
        self.macs_realised = 0.0
        self.macs_pruner = 0.0
        self.sample_s = 0.0

    def add_call(self, acc: Optional["tts.Accelerator"], images: int, seconds: float) -> None:
        self.images += images
        self.calls += 1
        self.sample_s += seconds
        if acc is None:
            return
        c = last_call_counts(acc)
        self.decisions += c["decisions"]
        self.reused += c["reused"]
        self.macs_dense += c["macs_dense"]
        self.macs_realised += c["macs_realised"]
        self.macs_pruner += c["macs_pruner"]


def dense_macs_per_image(model: DiT, steps: int, cfg: float) -> float:
    """MACs of one image's sampling call with the untouched model (rows x steps forwards, embedders
    excluded as in the engine's count), by torch's FlopCounterMode."""
    from tts.flops import flop_counter_macs

    p = model.pos_embed
    size = model.config.input_size
    x = torch.zeros(1, model.in_channels, size, size, device=p.device, dtype=p.dtype)
    t = torch.zeros(1, dtype=torch.long, device=p.device)
    c = torch.zeros(1, model.config.hidden_size, device=p.device, dtype=p.dtype)
    with torch.no_grad():
        one = flop_counter_macs(lambda: model(x, t, t, c=c))
    return float(one * steps * (2 if cfg != 1.0 else 1))


def resolve_budget(model: DiT, method: Method) -> Method:
    """``toca:N@RHO`` / ``duca:N@RHO``: the fresh-token ratio that reuses RHO of the branch MACs at interval N."""
    if method.kind not in ("toca", "duca") or method.ratio is not None:
        return method
    ratio = tts.tokens.fresh_ratio_for(method.sparsity, method.n, mlp_share(model), alternate=method.kind == "duca")
    return dataclasses.replace(method, ratio=ratio)


def build_accelerator(model: DiT, method: Method, *, steps: int, cfg: float, calib_seed: int,
                      calibration: Optional[dict] = None) -> Any:
    """The accelerator of ``method`` (None for dense and ``ddim:K``); for ``diffusers:`` a
    :class:`DiffusersCache` on a converted copy (sample ``acc.model``). An FBCache budget is calibrated
    on ``calib_seed`` noise (never the evaluation's); what it found goes into ``calibration``."""
    if method.kind in ("dense", "ddim", "dpm"):
        return None
    if method.kind == "diffusers":
        from tts.adapters.dit_diffusers import DiffusersDiT

        wrapped = model if isinstance(model, DiffusersDiT) else DiffusersDiT.from_dit(model)
        if method.cache == "taylorseer":
            return DiffusersCache(wrapped, "taylorseer", interval=method.n, order=method.order, warmup=1)
        threshold = method.threshold
        if threshold is None:
            idx = range(CALIBRATION_IMAGES)
            labels = torch.tensor([i % model.config.num_classes for i in idx], device=model.pos_embed.device)
            noise = sample_noise(calib_seed, idx, (model.in_channels, model.config.input_size,
                                                   model.config.input_size))
            threshold, reached = calibrate_fbc_threshold(wrapped, method.sparsity, labels, noise, steps=steps,
                                                         cfg_scale=cfg)
            if calibration is not None:
                calibration.update(threshold=threshold, sparsity=reached, seed=calib_seed, images=CALIBRATION_IMAGES)
        return DiffusersCache(wrapped, "fbc", threshold=threshold)
    return install(model, resolve_budget(model, method), memory_width=model.config.hidden_size)
