"""A DDPM step with its per-step coefficients precomputed once per call.

``diffusers.DDPMScheduler.step`` spends most of its time in Python bookkeeping (finding the previous
timestep, indexing, scalar maths), which at small batch sizes costs as much as several skipped
decoder blocks. :class:`FastDDPM` computes the same coefficients with the same tensor operations up
front, so each step is five tensor ops and the result equals ``scheduler.step`` exactly.
"""
from __future__ import annotations

from typing import Optional

import torch

__all__ = ["FastDDPM"]


class FastDDPM:
    """Equivalent of ``DDPMScheduler.step`` for the configured ``scheduler.timesteps``.

    Supports epsilon/sample prediction, ``fixed_small`` variance, optional clipping (what Diffusion
    Policy uses); other configurations raise so that nothing silently differs.
    """

    def __init__(self, scheduler):
        cfg = scheduler.config
        if cfg.prediction_type not in ("epsilon", "sample"):
            raise NotImplementedError(f"FastDDPM: prediction_type={cfg.prediction_type!r} not supported")
        if cfg.variance_type != "fixed_small" or cfg.thresholding:
            raise NotImplementedError("FastDDPM supports variance_type='fixed_small' without thresholding")
        if scheduler.timesteps is None or scheduler.num_inference_steps is None:
            raise ValueError("call scheduler.set_timesteps(K) before building FastDDPM")
        self.prediction_type = cfg.prediction_type
        self.clip = float(cfg.clip_sample_range) if cfg.clip_sample else None
        self.timesteps = scheduler.timesteps.clone()
        ts = self.timesteps.tolist()
        ac = scheduler.alphas_cumprod
        self.coef: list[tuple] = []
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

    def __len__(self) -> int:
        return len(self.coef)

    def step(self, i: int, model_output: torch.Tensor, sample: torch.Tensor,
             generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """x_{t-1} from x_t at loop index ``i`` (timestep ``self.timesteps[i]``)."""
        sqrt_b, sqrt_a, c_x0, c_xt, std = self.coef[i]
        if self.prediction_type == "epsilon":
            x0 = (sample - sqrt_b * model_output) / sqrt_a
        else:
            x0 = model_output
        if self.clip is not None:
            x0 = x0.clamp(-self.clip, self.clip)
        prev = c_x0 * x0 + c_xt * sample
        if std is not None:
            from diffusers.utils.torch_utils import randn_tensor

            noise = randn_tensor(model_output.shape, generator=generator, device=model_output.device,
                                 dtype=model_output.dtype)
            prev = prev + std * noise
        return prev
