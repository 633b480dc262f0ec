"""What the two model trainers (eval/train_policy.py, eval/train_dit.py) share: an EMA of the
weights and the resumable training state (model, EMA, optimiser, LR schedule, step, losses, RNG)."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable

import torch

from tts.io import atomic_path

__all__ = ["EMA", "save_training_state", "restore_training_state"]


class EMA:
    """Exponential moving average of ``model``'s weights (buffers copied); ``decay(n)`` gives the
    decay at update ``n`` (1, 2, ...)."""

    def __init__(self, model: torch.nn.Module, decay: Callable[[int], float]):
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.decay, self.step = decay, 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.step += 1
        d = self.decay(self.step)
        for e, p in zip(self.model.parameters(), model.parameters()):
            e.mul_(d).add_(p.detach(), alpha=1 - d)
        for e, b in zip(self.model.buffers(), model.buffers()):
            e.copy_(b)


def save_training_state(path: Path, weights_key: str, model: torch.nn.Module, ema: EMA, opt, sched, step: int,
                        losses: list, **extra: Any) -> None:
    """Write the training state atomically; the weights under ``weights_key``, ``extra`` alongside."""
    with atomic_path(path) as tmp:
        torch.save({**extra, weights_key: model.state_dict(), "ema": ema.model.state_dict(), "ema_step": ema.step,
                    "opt": opt.state_dict(), "sched": sched.state_dict(), "step": step, "losses": losses,
                    "rng": torch.get_rng_state()}, tmp)


def restore_training_state(st: dict, weights_key: str, model: torch.nn.Module, ema: EMA, opt, sched) -> tuple[int, list]:
    """Load a :func:`save_training_state` dict into the objects; returns (step, losses)."""
    model.load_state_dict(st[weights_key])
    ema.model.load_state_dict(st["ema"])
    ema.step = st["ema_step"]
    opt.load_state_dict(st["opt"])
    sched.load_state_dict(st["sched"])
    torch.set_rng_state(st["rng"])
    return st["step"], st["losses"]
