"""Diffusion Policy (low-dim, transformer) around :class:`TransformerForDiffusion`: normaliser,
observation history, action chunking, DDPM / DDIM / DPM-Solver++ sampling, checkpoint loading.

- ``predict_action({key: [B, To, dim]})`` returns ``action`` [B, Ta, Da] (executed) and
  ``action_pred`` [B, H, Da]; ``reset()`` marks an episode boundary (tts clears its rollout cache).
- Checkpoints: ours are ``<name>.safetensors`` (EMA weights + normaliser) next to ``<name>.json``
  (config); official Diffusion Policy ``.ckpt`` files (a torch pickle with ``cfg`` and
  ``state_dicts``) load without the diffusion_policy package. Pickle runs code on load: only pass
  files you trust (``trust_pickle=True`` is required when the file holds more than tensors).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn as nn

from tts.io import atomic_path, checkpoint_pair
from tts.spec import Target, register_model_adapter

from .diffusion_policy import DPTransformerConfig, TransformerForDiffusion, encode_condition, has_condition_encoder
from .diffusion_policy import _adapt as _adapt_model
from .schedulers import fast_step_for

Generators = Union[None, torch.Generator, Sequence[torch.Generator]]
LOWDIM_FORMAT = "tts-dp-lowdim-v1"
HYBRID_FORMAT = "tts-dp-hybrid-image-v1"

__all__ = ["SCHEDULERS", "SPACINGS", "Normalizer", "PolicyConfig", "DiffusionTransformerLowdimPolicy", "load_policy", "save_policy"]


class Normalizer(nn.Module):
    """Per-dimension affine map to [-1, 1] (Diffusion Policy's ``limits`` mode): y = x * scale + offset."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("scale", torch.ones(dim))
        self.register_buffer("offset", torch.zeros(dim))

    @torch.no_grad()
    def fit(self, data: torch.Tensor, range_eps: float = 1e-4) -> "Normalizer":
        """Fit a per-dimension min-max map of ``data`` [..., D] onto [-1, 1]; returns self."""
        x = data.reshape(-1, data.shape[-1]).double()
        lo, hi = x.min(0).values, x.max(0).values
        rng = hi - lo
        flat = rng < range_eps  # constant dims: centre them, do not blow them up
        rng[flat] = 2.0
        scale = 2.0 / rng
        offset = -1.0 - scale * lo
        offset[flat] = -lo[flat]
        self.scale.copy_(scale.float())
        self.offset.copy_(offset.float())
        return self

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Raw values -> [-1, 1]."""
        return x * self.scale + self.offset

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        """[-1, 1] -> raw values."""
        return (y - self.offset) / self.scale


@dataclass
class PolicyConfig:
    """A low-dim policy: the transformer's arguments, observation keys and sizes, horizons, sampler."""

    model: dict
    obs_keys: Sequence[str]
    obs_dims: Sequence[int]
    action_dim: int
    horizon: int = 10
    n_obs_steps: int = 2
    n_action_steps: int = 8
    num_train_timesteps: int = 100
    num_inference_steps: int = 100
    scheduler: str = "ddpm"  # "ddpm" | "ddim" | "dpm" (DPM-Solver++, 2nd order multistep)
    extra: dict = field(default_factory=dict)
    timestep_spacing: Optional[str] = None  # None: the scheduler's default as Diffusion Policy sets it


SCHEDULERS = ("ddpm", "ddim", "dpm")
SPACINGS = ("leading", "trailing", "linspace")


def _make_scheduler(cfg: PolicyConfig):
    """DDPM / DDIM as Diffusion Policy configures them (squared-cosine betas, clipped x0, epsilon
    prediction); ``dpm``: DPM-Solver++ (2nd order multistep), whose dynamic thresholding with
    ``sample_max_value=1`` is the same clipping of x0 to [-1, 1]."""
    from diffusers import DDIMScheduler, DDPMScheduler, DPMSolverMultistepScheduler

    kw = dict(num_train_timesteps=cfg.num_train_timesteps, beta_schedule="squaredcos_cap_v2", prediction_type="epsilon")
    if cfg.timestep_spacing is not None:
        if cfg.timestep_spacing not in SPACINGS:
            raise ValueError(f"timestep_spacing must be one of {SPACINGS}, got {cfg.timestep_spacing!r}")
        kw["timestep_spacing"] = cfg.timestep_spacing
    if cfg.scheduler == "ddim":
        s = DDIMScheduler(set_alpha_to_one=True, steps_offset=0, clip_sample=True, **kw)
    elif cfg.scheduler == "ddpm":
        s = DDPMScheduler(variance_type="fixed_small", clip_sample=True, **kw)
    elif cfg.scheduler == "dpm":
        s = DPMSolverMultistepScheduler(algorithm_type="dpmsolver++", solver_order=2, thresholding=True,
                                        sample_max_value=1.0, **kw)
    else:
        raise ValueError(f"scheduler must be one of {SCHEDULERS}, got {cfg.scheduler!r}")
    s.set_timesteps(cfg.num_inference_steps)
    return s


class DiffusionTransformerLowdimPolicy(nn.Module):
    """DP-T with observations as condition tokens (``obs_as_cond``), as in Chi et al. 2023."""

    def __init__(self, cfg: PolicyConfig):
        super().__init__()
        self.cfg = cfg
        self.model = TransformerForDiffusion(DPTransformerConfig(**cfg.model))
        self.obs_normalizer = Normalizer(sum(cfg.obs_dims))
        self.action_normalizer = Normalizer(cfg.action_dim)
        self.set_sampler()

    @property
    def device(self) -> torch.device:
        """The device of the policy's weights."""
        return self.model.pos_emb.device

    def set_sampler(self, scheduler: Optional[str] = None, steps: Optional[int] = None,
                    spacing: Optional[str] = None) -> "DiffusionTransformerLowdimPolicy":
        """Switch the sampler (``"ddpm"`` / ``"ddim"`` / ``"dpm"``), its number of denoising steps and/or
        its timestep spacing (``"leading"``, ``"trailing"``, ``"linspace"``; None keeps the current
        one when the scheduler stays, else the scheduler's default), e.g. the fewer-steps baseline
        DDIM-10. The weights are untouched."""
        steps = self.cfg.num_inference_steps if steps is None else int(steps)
        if not 1 <= steps <= self.cfg.num_train_timesteps:
            raise ValueError(f"steps must be in 1..{self.cfg.num_train_timesteps}, got {steps}")
        scheduler = scheduler or self.cfg.scheduler
        if spacing is None and scheduler == self.cfg.scheduler:
            spacing = self.cfg.timestep_spacing
        self.cfg = replace(self.cfg, scheduler=scheduler, num_inference_steps=steps, timestep_spacing=spacing)
        self.scheduler = _make_scheduler(self.cfg)
        self._fast = fast_step_for(self.scheduler)
        return self

    def reset(self) -> None:
        """Episode boundary (no state of its own; tts hooks it to clear the rollout cache)."""

    def obs_vector(self, obs: dict[str, Any]) -> torch.Tensor:
        """Concatenate the observation keys in config order: [B, To, obs_dim]."""
        parts = []
        for k in self.cfg.obs_keys:
            if k not in obs:
                raise KeyError(f"observation key {k!r} missing; policy expects {list(self.cfg.obs_keys)}")
            parts.append(torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32))
        x = torch.cat(parts, dim=-1)
        if x.shape[-1] != sum(self.cfg.obs_dims):
            raise ValueError(f"observation dim {x.shape[-1]} != expected {sum(self.cfg.obs_dims)}")
        return x.to(self.device)

    def predict_action(self, obs: dict[str, Any], generator: Generators = None, *,
                       enable_grad: bool = False) -> dict[str, torch.Tensor]:
        """Sample an action chunk. ``generator``: one ``torch.Generator`` for the batch, or a list
        with one per sample (each sample's noise then does not depend on the batch it is in).
        ``enable_grad``: keep the autograd graph (pruner training; the policy's weights stay frozen)."""
        with torch.set_grad_enabled(enable_grad):
            return self._predict(obs, generator)

    def condition(self, obs: dict[str, Any]) -> torch.Tensor:
        """The transformer's condition [B, n_obs_steps, cond_dim] of one call: the normalised
        observation vectors of the last ``n_obs_steps`` frames (image policies encode here, once)."""
        nobs = self.obs_normalizer.normalize(self.obs_vector(obs))
        if nobs.dim() != 3 or nobs.shape[1] < self.cfg.n_obs_steps:
            raise ValueError(f"observations must be [B, >= {self.cfg.n_obs_steps}, dim], got {tuple(nobs.shape)}")
        return nobs[:, -self.cfg.n_obs_steps:]

    def _predict(self, obs: dict[str, Any], generator: Generators) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        cond = self.condition(obs)
        B = cond.shape[0]
        if isinstance(generator, (list, tuple)) and len(generator) != B:
            raise ValueError(f"got {len(generator)} generators for a batch of {B}")
        from diffusers.utils.torch_utils import randn_tensor  # diffusers: an optional dependency

        x = randn_tensor((B, cfg.horizon, cfg.action_dim), generator=generator, device=self.device,
                         dtype=torch.float32)
        if self._fast is not None:
            memory = self.model.condition_memory(self._fast.timesteps, cond)
            for i, t in enumerate(self._fast.timesteps):
                x = self._fast.step(i, self.model(x, t, cond, memory=memory[:, i]), x, generator)
        else:  # a stateful multistep solver: fresh state for every call
            self.scheduler.set_timesteps(cfg.num_inference_steps)
            memory = self.model.condition_memory(self.scheduler.timesteps, cond)
            for i, t in enumerate(self.scheduler.timesteps):
                out = self.model(x, t, cond, memory=memory[:, i])
                x = self.scheduler.step(out, t, x, generator=generator).prev_sample
        action_pred = self.action_normalizer.unnormalize(x)
        start = cfg.n_obs_steps - 1
        return {"action": action_pred[:, start:start + cfg.n_action_steps], "action_pred": action_pred}

    def compute_loss(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """DDPM epsilon loss on normalised data; obs [B, To, obs_dim], action [B, H, Da]."""
        cond = self.obs_normalizer.normalize(obs)[:, : self.cfg.n_obs_steps]
        a = self.action_normalizer.normalize(action)
        noise = torch.randn_like(a)
        t = torch.randint(0, self.cfg.num_train_timesteps, (a.shape[0],), device=a.device)
        noisy = self.scheduler.add_noise(a, noise, t)
        return nn.functional.mse_loss(self.model(noisy, t, cond), noise)


def save_policy(policy: DiffusionTransformerLowdimPolicy, path: Path, metadata: Optional[dict] = None,
                dtype: torch.dtype = torch.float16) -> None:
    """``path.safetensors`` (weights, stored as ``dtype``; normaliser in fp32) + ``path.json``."""
    from safetensors.torch import save_file

    weights, meta_path = checkpoint_pair(path)
    state = {k: (v.to(dtype) if k.startswith(("model.", "obs_encoder.")) and v.is_floating_point() else v).contiguous().cpu()
             for k, v in policy.state_dict().items()}
    with atomic_path(weights) as tmp:
        save_file(state, str(tmp))
    image_cfg = getattr(policy, "image_cfg", None)
    meta = {"format": HYBRID_FORMAT if image_cfg is not None else LOWDIM_FORMAT, "config": asdict(policy.cfg),
            "metadata": metadata or {}}
    if image_cfg is not None:
        meta["image_encoder"] = asdict(image_cfg)
    with atomic_path(meta_path) as tmp:
        tmp.write_text(json.dumps(meta, indent=2))


def official_run_fields(cfg: Any) -> dict:
    """Horizons and sampler of an official Diffusion Policy run config (top level, else ``policy``)."""
    pol = cfg["policy"]
    sched = dict(pol.get("noise_scheduler", {}))
    get = lambda k: cfg[k] if k in cfg else pol[k]  # noqa: E731
    train = int(sched.get("num_train_timesteps", 100))
    return dict(horizon=int(get("horizon")), n_obs_steps=int(get("n_obs_steps")),
                n_action_steps=int(get("n_action_steps")), num_train_timesteps=train,
                num_inference_steps=int(pol.get("num_inference_steps") or train))


def load_official_normalizer(norm: Normalizer, sd: dict, keys: Sequence[str]) -> None:
    """Fill ``norm`` from the per-key ``normalizer.params_dict.<key>`` scale/offset of an official
    state dict, concatenated in ``keys`` order."""
    if not keys:
        return
    for what in ("scale", "offset"):
        parts = []
        for k in keys:
            name = f"normalizer.params_dict.{k}.{what}"
            if name not in sd:
                raise ValueError(f"official checkpoint has no {name}")
            parts.append(sd[name].reshape(-1).float())
        getattr(norm, what).copy_(torch.cat(parts))


def _from_official(payload: dict) -> DiffusionTransformerLowdimPolicy:
    cfg = payload["cfg"]
    cfg = {k: cfg[k] for k in cfg} if not isinstance(cfg, dict) else cfg
    states = payload["state_dicts"]
    sd = states.get("ema_model") or states["model"]
    if "shape_meta" in cfg["policy"] or any(k.startswith("obs_encoder.") for k in sd):
        from .dp_image_policy import hybrid_policy_from_official

        return hybrid_policy_from_official(cfg, sd)
    pol, task = cfg["policy"], cfg.get("task", {})
    m = dict(pol["model"])
    m.pop("_target_", None)
    model_cfg = {k: m[k] for k in DPTransformerConfig.__dataclass_fields__ if k in m}
    obs_dim, action_dim = int(cfg.get("obs_dim", task.get("obs_dim"))), int(cfg.get("action_dim", task.get("action_dim")))
    pcfg = PolicyConfig(model=model_cfg, obs_keys=("obs",), obs_dims=(obs_dim,), action_dim=action_dim,
                        **official_run_fields(cfg))
    policy = DiffusionTransformerLowdimPolicy(pcfg)
    policy.model.load_state_dict({k[len("model."):]: v for k, v in sd.items() if k.startswith("model.")})
    load_official_normalizer(policy.obs_normalizer, sd, ["obs"])
    load_official_normalizer(policy.action_normalizer, sd, ["action"])
    return policy


def load_policy(path: Path, trust_pickle: bool = False) -> DiffusionTransformerLowdimPolicy:
    """Load ours (``.safetensors`` + ``.json``) or an official Diffusion Policy ``.ckpt``."""
    path = Path(path)
    if path.suffix == ".ckpt":
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # the official format pickles an OmegaConf config
            if not trust_pickle:
                raise ValueError(
                    f"{path} holds Python objects besides tensors (its config); loading it runs "
                    "pickled code. Pass trust_pickle=True only for files you trust."
                ) from e
            payload = torch.load(path, map_location="cpu", weights_only=False)
        if "state_dicts" not in payload or "cfg" not in payload:
            raise ValueError(f"{path} is not a Diffusion Policy checkpoint (needs 'cfg' and 'state_dicts')")
        return _from_official(payload).eval()
    from safetensors.torch import load_file

    weights, meta_path = checkpoint_pair(path)
    for p in (meta_path, weights):
        if not p.exists():
            raise FileNotFoundError(f"{p} not found (a tts policy is a .safetensors + .json pair)")
    meta = json.loads(meta_path.read_text())
    if meta.get("format") == LOWDIM_FORMAT:
        policy = DiffusionTransformerLowdimPolicy(PolicyConfig(**meta["config"]))
    elif meta.get("format") == HYBRID_FORMAT:
        from .dp_image_policy import DiffusionTransformerHybridImagePolicy, ImageEncoderConfig

        policy = DiffusionTransformerHybridImagePolicy(PolicyConfig(**meta["config"]),
                                                       ImageEncoderConfig(**meta["image_encoder"]))
    else:
        raise ValueError(f"{meta_path}: unknown format {meta.get('format')!r}")
    state = {k: v.float() if v.is_floating_point() else v for k, v in load_file(str(weights)).items()}
    missing, unexpected = policy.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(f"{weights} does not match its config: missing {missing[:5]}, unexpected {unexpected[:5]}")
    return policy.eval()


def _policy_scheduler(policy: Any) -> Any:
    """The policy's diffusers-style scheduler: ``noise_scheduler`` (official) or ``scheduler`` (ours)."""
    for name in ("noise_scheduler", "scheduler"):
        s = getattr(policy, name, None)
        if s is not None and hasattr(s, "timesteps"):
            return s
    return None


def _condition_from_inputs(policy: Any, model: nn.Module):
    """``condition_of`` for a policy whose loop calls the transformer as ``model(x, t, cond)`` at every
    step: the memory of all K steps from the scheduler's timesteps (set before its loop starts) and
    the ``cond`` argument of step 0, built from the official attributes."""

    def condition_of(args: tuple, kwargs: dict) -> torch.Tensor:
        scheduler = _policy_scheduler(policy)
        cond = kwargs.get("cond", args[2] if len(args) > 2 else None)
        sample = kwargs.get("sample", args[0] if args else None)
        return encode_condition(model, scheduler.timesteps, cond,
                                batch=None if sample is None else sample.shape[0])

    return condition_of


def _adapt(policy: Any) -> Optional[Target]:
    """A Diffusion Policy policy (ours or the official classes): its ``model`` is a DP transformer,
    ``predict_action`` starts a sampling call and ``reset`` ends an episode."""
    if not (callable(getattr(policy, "predict_action", None)) and isinstance(getattr(policy, "model", None), nn.Module)):
        return None
    model = policy.model
    target = _adapt_model(model)
    if target is None:
        return None
    target.boundaries = [(policy, "predict_action")]
    target.episode_resets = [(policy, "reset")] if callable(getattr(policy, "reset", None)) else []
    target.description = f"Diffusion Policy ({type(policy).__name__})"
    encoder = getattr(policy, "obs_encoder", None)
    if isinstance(encoder, nn.Module):  # an image encoder, run once per call before the loop: timed
        target.timers = [(encoder, "forward", "image_encoder")]
    if target.condition is None and has_condition_encoder(model):
        if _policy_scheduler(policy) is not None:
            target.condition_of = _condition_from_inputs(policy, model)
            target.condition_note = ""
        else:
            target.condition_note = (f"{type(policy).__name__} has no noise_scheduler with the timesteps of a "
                                     "sampling call, and its model no condition_memory(timesteps, cond) method")
    return target


register_model_adapter("Diffusion Policy policy", _adapt)
