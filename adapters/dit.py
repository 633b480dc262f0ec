"""DiT (Peebles & Xie 2023) in the layout of the official facebookresearch/DiT code, built on timm's
``Attention`` / ``Mlp`` with adaLN-Zero modulation, and its tts block family.

Parameter names follow the official ``models.py`` so that an official checkpoint's state dict
(e.g. ``DiT-XL-2-256x256.pt``) loads unchanged. Written from the paper and the checkpoint layout.

Branches of a DiT block (official forward ``x + gate * f(modulate(norm(x), shift, scale))``):
``attn`` (gated self-attention) and ``mlp`` (gated MLP). ``adaLN_modulation(c)`` is shared by both
and evaluated only if one of them computes. Any block with the attributes ``norm1, attn, norm2, mlp,
adaLN_modulation`` where ``attn``/``mlp`` are timm's ``Attention``/``Mlp`` is recognised, so users'
own copies of the DiT file work too.

Class-conditional sampling with tts: :meth:`DiT.condition_memory` computes DiT's conditioning vector
``c = t_embedder(t_k) + y_embedder(y)`` for all K sampling steps in one batched call ([B, K, 1, hidden];
the adapter declares it as ``Target.condition``, so a learned :class:`tts.Pruner` reads it), and
``forward(x, t, y, c=memory[:, k])`` skips the embedders. :func:`sample_dit` is DiT's DDIM/DDPM
sampling loop with batched classifier-free guidance ([cond; uncond] rows, guidance on eps only).
:func:`load_dit` reads our ``.safetensors`` + ``.json`` pair or an official ``DiT-XL-2-256x256.pt``.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import torch
import torch.nn as nn

from tts.flops import register_mac_rule
from tts.io import checkpoint_pair
from tts.spec import BlockSpec, BranchSpec, Lazy, Target, register_block_family, register_model_adapter

__all__ = ["DiTConfig", "DiT", "DiTBlock", "DIT_CONFIGS", "dit_block_spec", "save_dit", "load_dit",
           "dit_config_from_state_dict", "dit_scheduler", "sample_dit", "DIT_DOWNLOAD_URL"]


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """adaLN modulation: ``x * (1 + scale) + shift`` per sample."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


@dataclass(frozen=True)
class DiTConfig:
    """Architecture of a DiT (the official DiT's arguments; presets in :data:`DIT_CONFIGS`)."""

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
for _name, _cfg in list(DIT_CONFIGS.items()):  # the paper's /4 and /8 variants (same widths, larger patches)
    for _p in (4, 8):
        DIT_CONFIGS[_name[:-1] + str(_p)] = DiTConfig(depth=_cfg.depth, hidden_size=_cfg.hidden_size, patch_size=_p,
                                                      num_heads=_cfg.num_heads)
del _name, _cfg, _p


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
        """Sinusoidal embedding [N, dim] of the (possibly fractional) timesteps ``t`` [N]."""
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
    """The official DiT block: adaLN-Zero modulated self-attention and MLP (timm ``Attention`` / ``Mlp``)."""

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
    """DiT's output layer: adaLN-modulated layer norm and a linear map to patches."""

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
        """Patch tokens [N, T, p*p*C] -> images [N, C, H, W]."""
        c, p = self.out_channels, self.patch_size
        h = w = int(x.shape[1] ** 0.5)
        x = x.reshape(x.shape[0], h, w, p, p, c)
        x = torch.einsum("nhwpqc->nchpwq", x)
        return x.reshape(x.shape[0], c, h * p, w * p)

    def condition_memory(self, timesteps: Any, y: torch.Tensor) -> torch.Tensor:
        """DiT's conditioning vector for all K sampling timesteps at once: [B, K, 1, hidden].

        ``memory[:, k, 0] = t_embedder(t_k) + y_embedder(y, train=False)`` (one batched embedder call for
        the K timesteps, one for the B labels; no class dropout). Pass ``c=memory[:, k]`` to
        :meth:`forward` at step k. Equal to the per-step embedders up to float round-off (a matmul's
        rows may differ in the last bit with the number of rows it is called on).
        """
        device = self.pos_embed.device
        timesteps = torch.as_tensor(timesteps, device=device).reshape(-1)
        y = torch.as_tensor(y, device=device).reshape(-1)
        t_emb = self.t_embedder(timesteps)  # [K, D]
        y_emb = self.y_embedder(y, False)  # [B, D]
        return (t_emb[None] + y_emb[:, None]).unsqueeze(2)

    def _check_condition(self, c: torch.Tensor, batch: int) -> torch.Tensor:
        h = self.pos_embed.shape[-1]
        if c.dim() == 3 and c.shape[1] == 1:  # a slice memory[:, k] of condition_memory's output
            c = c[:, 0]
        if c.dim() != 2 or c.shape[0] != batch or c.shape[1] != h:
            raise ValueError(f"c must be the conditioning vector [batch={batch}, hidden={h}] (or memory[:, k] "
                             f"of condition_memory, [{batch}, 1, {h}]); got {tuple(c.shape)}")
        return c

    def forward(self, x: torch.Tensor, t: torch.Tensor, y: torch.Tensor,
                c: Optional[torch.Tensor] = None) -> torch.Tensor:
        """x [B, C, H, W], t [B], y [B] -> [B, out_channels, H, W].

        ``c``: a precomputed conditioning vector for this step ([B, hidden] or ``memory[:, k]`` of
        :meth:`condition_memory`); the timestep and label embedders are then skipped (``t`` only serves
        step tracking, ``y`` is unused; no class dropout). With ``c=None`` this is the official forward.
        """
        x = self.x_embedder(x) + self.pos_embed
        if c is None:
            c = self.t_embedder(t) + self.y_embedder(y, self.training)
        else:
            c = self._check_condition(c, x.shape[0])
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


# ------------------------------------------------------------------------------- checkpoints
DIT_FORMAT = "tts-dit-v1"
DIT_DOWNLOAD_URL = "https://dl.fbaipublicfiles.com/DiT/models/{name}"  # official pretrained state dicts
_OFFICIAL_SUFFIXES = (".pt", ".pth", ".bin")


def save_dit(model: DiT, path: Union[str, Path], metadata: Optional[dict] = None,
             dtype: Optional[torch.dtype] = None) -> None:
    """Write ``<path>.safetensors`` (weights, optionally cast to ``dtype``) and ``<path>.json`` (the
    :class:`DiTConfig` and ``metadata``), each atomically."""
    from safetensors.torch import save_file

    from tts.io import atomic_path

    weights, meta = checkpoint_pair(Path(path))
    state = {k: (v.to(dtype) if dtype is not None and v.is_floating_point() else v).detach().contiguous().cpu()
             for k, v in model.state_dict().items()}
    with atomic_path(weights) as tmp:
        save_file(state, str(tmp))
    doc = {"format": DIT_FORMAT, "config": asdict(model.config), "metadata": metadata or {}}
    with atomic_path(meta) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2) + "\n")


def _missing_model_error(path: Path) -> FileNotFoundError:
    official = (
        "an official facebookresearch/DiT state dict: download DiT-XL-2-256x256.pt from\n"
        f"    {DIT_DOWNLOAD_URL.format(name='DiT-XL-2-256x256.pt')} (512x512: DiT-XL-2-512x512.pt)\n"
        "    into checkpoints/ and pass its path (checkpoints/DiT-XL-2-256x256.pt); latent DiTs also need the\n"
        "    Stable Diffusion VAE (a diffusers folder of stabilityai/sd-vae-ft-ema) to decode images")
    if path.suffix in _OFFICIAL_SUFFIXES:
        return FileNotFoundError(f"no DiT checkpoint at {path}. Expected {official}.\n"
                                 "  (A tts DiT trained here instead: python eval/train_dit.py --out PATH, "
                                 "then pass PATH.)")
    weights, meta = checkpoint_pair(path)
    return FileNotFoundError(
        f"no DiT checkpoint at {path}. Expected either\n"
        f"  - a tts DiT: {weights} + {meta} (train one: python eval/train_dit.py --out {weights.with_suffix('')}), or\n"
        f"  - {official}.")


def _heads_for(hidden: int, depth: int, patch: int) -> Optional[int]:
    for cfg in DIT_CONFIGS.values():
        if (cfg.hidden_size, cfg.depth, cfg.patch_size) == (hidden, depth, patch):
            return cfg.num_heads
    return None


def dit_config_from_state_dict(state: dict, config: Union[None, str, DiTConfig] = None,
                               num_heads: Optional[int] = None) -> DiTConfig:
    """Infer the :class:`DiTConfig` of an official-layout state dict from its tensor shapes.

    Everything but the number of attention heads follows from the shapes; heads come from ``num_heads``,
    from ``config`` (a :data:`DIT_CONFIGS` name such as ``"DiT-XL/2"``, checked against the shapes), or
    from the official config with the same width, depth and patch size. A :class:`DiTConfig` given as
    ``config`` is returned as is. The label table is assumed to hold the extra CFG "null" row, as in every
    official checkpoint.
    """
    if isinstance(config, DiTConfig):
        return config
    need = ["x_embedder.proj.weight", "pos_embed", "y_embedder.embedding_table.weight", "final_layer.linear.weight",
            "blocks.0.mlp.fc1.weight"]
    missing = [k for k in need if k not in state]
    if missing:
        raise ValueError(f"not an official-layout DiT state dict: missing {missing} "
                         f"(first keys: {list(state)[:5]})")
    hidden, in_ch, patch, _ = state["x_embedder.proj.weight"].shape
    num_patches = state["pos_embed"].shape[1]
    grid = math.isqrt(num_patches)
    if grid * grid != num_patches:
        raise ValueError(f"pos_embed has {num_patches} positions, not a square grid")
    depth = 1 + max(int(m.group(1)) for k in state if (m := re.match(r"blocks\.(\d+)\.", k)))
    out_ch = state["final_layer.linear.weight"].shape[0] // (patch * patch)
    if out_ch not in (in_ch, 2 * in_ch):
        raise ValueError(f"final layer predicts {out_ch} channels for {in_ch} input channels (expected "
                         f"{in_ch} or {2 * in_ch} with learned sigma)")
    mlp_ratio = state["blocks.0.mlp.fc1.weight"].shape[0] / hidden
    if isinstance(config, str):
        if config not in DIT_CONFIGS:
            raise ValueError(f"unknown DiT config {config!r}; known: {sorted(DIT_CONFIGS)}")
        named = DIT_CONFIGS[config]
        if (named.hidden_size, named.depth, named.patch_size) != (hidden, depth, patch):
            raise ValueError(f"{config} has hidden {named.hidden_size}, depth {named.depth}, patch "
                             f"{named.patch_size}; the state dict has {hidden}, {depth}, {patch}")
        num_heads = num_heads or named.num_heads
    elif config is not None:
        raise TypeError(f"config must be a DIT_CONFIGS name or a DiTConfig, got {type(config).__name__}")
    num_heads = num_heads or _heads_for(hidden, depth, patch)
    if num_heads is None:
        raise ValueError(f"cannot infer the number of attention heads of a DiT with hidden {hidden}, depth "
                         f"{depth}, patch {patch} from its weights: pass num_heads= (or config=DiTConfig(...))")
    return DiTConfig(input_size=grid * patch, patch_size=patch, in_channels=in_ch, hidden_size=hidden, depth=depth,
                     num_heads=num_heads, mlp_ratio=mlp_ratio, class_dropout_prob=0.1,
                     num_classes=state["y_embedder.embedding_table.weight"].shape[0] - 1,
                     learn_sigma=out_ch == 2 * in_ch)


def load_dit(path: Union[str, Path], config: Union[None, str, DiTConfig] = None, num_heads: Optional[int] = None,
             map_location: Union[str, torch.device] = "cpu") -> DiT:
    """Load a DiT in eval mode (float32) from our ``<path>.safetensors`` + ``<path>.json`` pair (see
    :func:`save_dit`) or from an official facebookresearch/DiT ``.pt`` state dict (e.g.
    ``DiT-XL-2-256x256.pt``; read with ``torch.load(weights_only=True)``, config from the tensor shapes,
    see :func:`dit_config_from_state_dict`). A training checkpoint ``{"model", "ema", ...}`` uses ``ema``.
    ``model.checkpoint_info`` records the source and, for ours, the saved metadata. A directory is a
    diffusers DiT (a ``DiTPipeline`` folder or its ``transformer/``), returned as a
    :class:`~tts.adapters.dit_diffusers.DiffusersDiT` with the same calling convention.
    """
    path = Path(path)
    if path.is_dir():
        from .dit_diffusers import load_diffusers_dit

        return load_diffusers_dit(path, map_location)
    if path.suffix in _OFFICIAL_SUFFIXES:
        if not path.is_file():
            raise _missing_model_error(path)
        try:
            state = torch.load(path, map_location=map_location, weights_only=True)
        except Exception as e:  # pickled Python objects (e.g. an argparse Namespace in a training checkpoint)
            raise ValueError(f"{path} is not a plain tensor state dict ({type(e).__name__}: {e}); save "
                             "torch.load(...)['ema'] of a DiT training checkpoint as its own file") from e
        if isinstance(state, dict) and isinstance(state.get("ema", state.get("model")), dict):
            state = state.get("ema", state.get("model"))
        if not isinstance(state, dict):
            raise ValueError(f"{path} holds a {type(state).__name__}, not a state dict")
        cfg = dit_config_from_state_dict(state, config, num_heads)
        info = {"source": str(path), "format": "official-state-dict"}
    else:
        weights, meta = checkpoint_pair(path)
        if not (weights.is_file() and meta.is_file()):
            raise _missing_model_error(path)
        from safetensors.torch import load_file

        doc = json.loads(meta.read_text())
        if doc.get("format") != DIT_FORMAT:
            raise ValueError(f"{meta} is not a tts DiT checkpoint (format {doc.get('format')!r}, expected {DIT_FORMAT!r})")
        cfg = config if isinstance(config, DiTConfig) else DiTConfig(**doc["config"])
        state = load_file(str(weights), device=str(map_location))
        info = {"source": str(weights), "format": DIT_FORMAT, "metadata": doc.get("metadata", {})}
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    model = DiT(cfg)
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(f"{path} does not fit {cfg}: missing {missing[:5]}, unexpected {unexpected[:5]}")
    model.checkpoint_info = info
    return model.to(map_location).eval()


# ----------------------------------------------------------------------------------- sampling
DIT_BETAS = {"num_train_timesteps": 1000, "beta_start": 1e-4, "beta_end": 0.02, "beta_schedule": "linear"}


def dit_scheduler(kind: str = "ddim", steps: int = 50, learn_sigma: bool = False) -> Any:
    """A diffusers scheduler with DiT's training schedule (linear betas 1e-4..0.02 over 1000 steps), epsilon
    prediction, no clipping, ``steps`` evenly strided timesteps (as DiT's respacing).

    ``"ddim"``: eta = 0, the final step goes to alpha_bar = 1 (deterministic given the initial noise).
    ``"ddpm"``: ancestral steps, variance ``learned_range`` for models with learned sigma, else
    ``fixed_small``.
    ``"dpm"``: DPM-Solver++ (2nd order multistep, timesteps spaced as diffusers' default).
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if kind == "ddim":
        from diffusers import DDIMScheduler

        sched = DDIMScheduler(**DIT_BETAS, clip_sample=False, set_alpha_to_one=True, steps_offset=0,
                              prediction_type="epsilon", timestep_spacing="leading")
    elif kind == "ddpm":
        from diffusers import DDPMScheduler

        sched = DDPMScheduler(**DIT_BETAS, clip_sample=False, prediction_type="epsilon", timestep_spacing="leading",
                              variance_type="learned_range" if learn_sigma else "fixed_small")
    elif kind == "dpm":
        from diffusers import DPMSolverMultistepScheduler

        # fed eps only (diffusers' learned-variance branch of this solver assumes 3 channels)
        sched = DPMSolverMultistepScheduler(**DIT_BETAS, algorithm_type="dpmsolver++", solver_order=2,
                                            prediction_type="epsilon")
    else:
        raise ValueError(f"scheduler must be 'ddim', 'ddpm' or 'dpm' (or a diffusers scheduler), got {kind!r}")
    sched.set_timesteps(steps)
    return sched


def sample_dit(model: DiT, labels: Union[torch.Tensor, Sequence[int]], *, steps: int = 50, cfg_scale: float = 1.5,
               generator: Optional[torch.Generator] = None, scheduler: Any = "ddim",
               noise: Optional[torch.Tensor] = None, enable_grad: bool = False) -> torch.Tensor:
    """Class-conditional DiT sampling: images (or latents) in model space [B, C, H, W].

    labels: [B] class ids. noise: the initial x_T [B, C, H, W] (else drawn from ``generator``).
    cfg_scale: classifier-free guidance on the eps channels as in the official ``forward_with_cfg``; the
    batch is [cond; uncond] (labels, then the null class ``num_classes``), so a tts plan or pruner sees
    2B rows and may decide differently for the two halves. ``cfg_scale == 1`` runs the cond half only.
    scheduler: ``"ddim"`` / ``"ddpm"`` / ``"dpm"`` (see :func:`dit_scheduler`) or a diffusers scheduler (its
    ``set_timesteps(steps)`` is called). The condition is encoded once per call
    (:meth:`DiT.condition_memory`, where a tts pruner reads it) and each step runs
    ``model(x, t, y, c=memory[:, k])``. Learned-sigma outputs: the first C channels are eps.
    enable_grad: keep the autograd graph (pruner training; the model's weights stay frozen).
    """
    with torch.set_grad_enabled(enable_grad):
        return _sample_dit(model, labels, steps, cfg_scale, generator, scheduler, noise)


def _sample_dit(model, labels, steps, cfg_scale, generator, scheduler, noise) -> torch.Tensor:
    p = model.pos_embed
    device, dtype = p.device, p.dtype
    C, size = model.in_channels, model.config.input_size
    labels = torch.as_tensor(labels, device=device).long().reshape(-1)
    B = labels.shape[0]
    num_classes = model.y_embedder.num_classes
    if B == 0:
        raise ValueError("labels is empty")
    if int(labels.min()) < 0 or int(labels.max()) >= num_classes:
        raise ValueError(f"labels must lie in [0, {num_classes}), got {labels.min().item()}..{labels.max().item()}")
    use_cfg = float(cfg_scale) != 1.0
    if use_cfg and model.y_embedder.embedding_table.num_embeddings <= num_classes:
        raise ValueError("this DiT has no null class (trained without class dropout): use cfg_scale=1")
    if noise is None:
        noise = torch.randn(B, C, size, size, generator=generator, device=generator.device if generator else "cpu")
    if tuple(noise.shape) != (B, C, size, size):
        raise ValueError(f"noise must be [{B}, {C}, {size}, {size}], got {tuple(noise.shape)}")
    x = noise.to(device=device, dtype=dtype)
    if isinstance(scheduler, str):
        sched = dit_scheduler(scheduler, steps, learn_sigma=model.learn_sigma)
    else:
        sched = scheduler
        sched.set_timesteps(steps)
    learned_var = getattr(sched.config, "variance_type", None) in ("learned", "learned_range")
    y = torch.cat([labels, torch.full_like(labels, num_classes)]) if use_cfg else labels
    timesteps = sched.timesteps.to(device)
    memory = model.condition_memory(timesteps, y)  # [rows, K, 1, hidden]; a tts pruner observes it here
    rows = y.shape[0]
    for k, t in enumerate(timesteps):
        x_in = torch.cat([x, x]) if use_cfg else x
        out = model(x_in, t.expand(rows), y, c=memory[:, k])
        eps, rest = out[:, :C], out[:, C:]
        if use_cfg:
            cond, uncond = eps.chunk(2)
            eps, rest = uncond + cfg_scale * (cond - uncond), rest[:B]
        model_output = torch.cat([eps, rest], dim=1) if learned_var else eps
        x = sched.step(model_output, t, x, generator=generator).prev_sample
    return x


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


def _attention_probe(fn, block: nn.Module, *args: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the attention branch on timm's non-fused path (same result, same MACs) and catch the
    softmaxed attention where it enters ``attn_drop``: the attention each token receives [B, N]."""
    attn = block.attn
    caught: list[torch.Tensor] = []
    handle = attn.attn_drop.register_forward_hook(lambda mod, inp, out: caught.append(inp[0].detach()))
    fused, attn.fused_attn = attn.fused_attn, False
    try:
        delta = fn(*args)
    finally:
        attn.fused_attn = fused
        handle.remove()
    if len(caught) != 1:
        raise RuntimeError("the attention probe expected one softmax in timm's Attention (attn_drop input)")
    return delta, caught[0].mean(dim=(1, 2))  # [B, heads, Nq, Nk] -> mean over heads and queries


def dit_block_spec(block: nn.Module) -> BlockSpec:
    """The residual branches (attn, mlp) of an official-layout DiT block."""
    return BlockSpec(
        family="DiT block (timm Attention/Mlp + adaLN)",
        branches=(BranchSpec("attn", "self_attn", ("attn", "norm1"), probe=_attention_probe),
                  BranchSpec("mlp", "mlp", ("mlp", "norm2"))),
        forward=_dit_block_forward,
        residual=True,
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
    condition = (model, "condition_memory") if callable(getattr(model, "condition_memory", None)) else None
    return Target(denoiser=model, sites=discover_sites(model), supports_rollout=False, condition=condition,
                  description=f"DiT ({type(model).__name__})", chain=True)  # `for block in blocks: x = block(x, c)`


register_block_family("DiT block (timm Attention/Mlp + adaLN)", _match)
register_model_adapter("official-layout DiT", _adapt)
