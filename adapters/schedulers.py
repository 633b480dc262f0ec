"""Sampler steps with their per-step coefficients precomputed once per call.

``diffusers``' ``DDPMScheduler.step`` and ``DDIMScheduler.step`` spend most of their time in Python
bookkeeping (finding the previous timestep, indexing, scalar maths), which at small batch sizes
costs as much as several skipped decoder blocks. :class:`FastDDPM` and :class:`FastDDIM` compute the
same coefficients with the same tensor operations up front, so each step is a handful of tensor ops
and the result equals ``scheduler.step`` exactly (tested). Stateful multistep solvers (DPM-Solver++)
keep their own ``step``.
"""
from __future__ import annotations

from typing import Any, Optional

import torch

__all__ = ["FastDDPM", "FastDDIM", "fast_step_for"]


def _check_config(scheduler: Any, name: str) -> None:
    cfg = scheduler.config
    if cfg.prediction_type not in ("epsilon", "sample"):
        raise NotImplementedError(f"{name}: prediction_type={cfg.prediction_type!r} not supported")
    if cfg.thresholding:
        raise NotImplementedError(f"{name}: thresholding not supported")
    if scheduler.timesteps is None or scheduler.num_inference_steps is None:
        raise ValueError(f"call scheduler.set_timesteps(K) before building {name}")


class _FastStep:
    """Shared part: x0 from the model output (epsilon or sample prediction), optional clipping."""

    timesteps: torch.Tensor
    coef: list

    def __init__(self, scheduler: Any):
        cfg = scheduler.config
        self.prediction_type = cfg.prediction_type
        self.clip = float(cfg.clip_sample_range) if cfg.clip_sample else None
        self.timesteps = scheduler.timesteps.clone()

    def __len__(self) -> int:
        return len(self.coef)

    def _x0(self, sqrt_b: torch.Tensor, sqrt_a: torch.Tensor, model_output: torch.Tensor,
            sample: torch.Tensor) -> torch.Tensor:
        x0 = (sample - sqrt_b * model_output) / sqrt_a if self.prediction_type == "epsilon" else model_output
        return x0.clamp(-self.clip, self.clip) if self.clip is not None else x0


class FastDDPM(_FastStep):
    """Equivalent of ``DDPMScheduler.step`` for the configured ``scheduler.timesteps``.

    Supports epsilon/sample prediction, ``fixed_small`` variance, optional clipping (what Diffusion
    Policy uses); other configurations raise so that nothing silently differs.
    """

    def __init__(self, scheduler: Any):
        _check_config(scheduler, "FastDDPM")
        if scheduler.config.variance_type != "fixed_small":
            raise NotImplementedError("FastDDPM supports variance_type='fixed_small'")
        super().__init__(scheduler)
        ts = self.timesteps.tolist()
        ac = scheduler.alphas_cumprod
        self.coef = []
        for i, t in enumerate(ts):
            prev_t = ts[i + 1] if i + 1 < len(ts) else -1
            a_t = ac[t]
            a_prev = ac[prev_t] if prev_t >= 0 else scheduler.one
            b_t = 1 - a_t
            b_prev = 1 - a_prev
            cur_alpha = a_t / a_prev
            cur_beta = 1 - cur_alpha
            c_x0 = (a_prev ** 0.5 * cur_beta) / b_t
            c_xt = cur_alpha ** 0.5 * b_prev / b_t
            std = torch.clamp(b_prev / b_t * cur_beta, min=1e-20) ** 0.5 if t > 0 else None
            self.coef.append((b_t ** 0.5, a_t ** 0.5, c_x0, c_xt, std))

    def step(self, i: int, model_output: torch.Tensor, sample: torch.Tensor,
             generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """x_{t-1} from x_t at loop index ``i`` (timestep ``self.timesteps[i]``)."""
        sqrt_b, sqrt_a, c_x0, c_xt, std = self.coef[i]
        prev = c_x0 * self._x0(sqrt_b, sqrt_a, model_output, sample) + c_xt * sample
        if std is not None:
            from diffusers.utils.torch_utils import randn_tensor

            noise = randn_tensor(model_output.shape, generator=generator, device=model_output.device,
                                 dtype=model_output.dtype)
            prev = prev + std * noise
        return prev


class FastDDIM(_FastStep):
    """Equivalent of deterministic (eta = 0) ``DDIMScheduler.step`` for ``scheduler.timesteps``,
    whatever their spacing (the previous timestep is ``t - T // K``, as diffusers computes it)."""

    def __init__(self, scheduler: Any):
        _check_config(scheduler, "FastDDIM")
        super().__init__(scheduler)
        cfg = scheduler.config
        ac = scheduler.alphas_cumprod
        gap = cfg.num_train_timesteps // scheduler.num_inference_steps
        self.coef = []
        for t in self.timesteps.tolist():
            prev_t = t - gap
            a_t = ac[t]
            a_prev = ac[prev_t] if prev_t >= 0 else scheduler.final_alpha_cumprod
            b_t = 1 - a_t
            self.coef.append((b_t ** 0.5, a_t ** 0.5, a_prev ** 0.5, (1 - a_prev) ** 0.5))

    def step(self, i: int, model_output: torch.Tensor, sample: torch.Tensor,
             generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """x_{t-gap} from x_t at loop index ``i`` (no noise: ``generator`` is unused)."""
        sqrt_b, sqrt_a, sqrt_a_prev, sqrt_b_prev = self.coef[i]
        eps = model_output if self.prediction_type == "epsilon" else (sample - sqrt_a * model_output) / sqrt_b
        return sqrt_a_prev * self._x0(sqrt_b, sqrt_a, model_output, sample) + sqrt_b_prev * eps


def fast_step_for(scheduler: Any) -> Optional[_FastStep]:
    """The precomputed equivalent of ``scheduler.step`` (DDPM, DDIM), or None (e.g. DPM-Solver++)."""
    from diffusers import DDIMScheduler, DDPMScheduler

    if isinstance(scheduler, DDPMScheduler):
        return FastDDPM(scheduler)
    if isinstance(scheduler, DDIMScheduler):
        return FastDDIM(scheduler)
    return None
