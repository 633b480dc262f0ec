"""tts: Test-time Sparsity for diffusion transformers (Ji et al., CVPR 2026).

``tts.accelerate(model, directions=..., plan=...)`` hooks every residual branch of the model's
transformer blocks; before each denoising forward a plan (static) or a pruner (learned) decides, per
sample and branch, whether to compute it or to reuse a cached output from the *forward* (an earlier
block of the same kind), *timestep* (this branch at the previous computed step) or *rollout* (this
branch at the same step of the previous policy call) direction.
"""
from __future__ import annotations

from typing import Any, Callable, Iterable, Mapping, Optional, Union

import torch.nn as nn

from . import plans, tokens
from .engine import Accelerator, discover_sites
from .plans import Plan, check_directions, check_sparsity
from .pruner import Pruner, PrunerConfig, PrunerModule, PrunerPlan, StaticRouter, load_pruner, save_pruner
from .spec import BlockSpec, BranchSpec, Lazy, Target, model_adapters, register_block_family, register_model_adapter
from .summary import Summary

__all__ = [
    "accelerate",
    "Accelerator",
    "BlockSpec",
    "BranchSpec",
    "Lazy",
    "Plan",
    "Pruner",
    "PrunerConfig",
    "PrunerPlan",
    "StaticRouter",
    "load_pruner",
    "save_pruner",
    "Summary",
    "Target",
    "plans",
    "tokens",
    "register_block_family",
    "register_model_adapter",
    "resolve_target",
]
__version__ = "0.1.0"

BlocksArg = Optional[Mapping[str, Union[BlockSpec, Callable[[nn.Module], BlockSpec]]]]


def resolve_target(model: Any, blocks: BlocksArg = None) -> Target:
    """Find the denoiser, its branch sites and call/episode boundaries of ``model``."""
    from . import adapters  # noqa: F401  (registers the built-in families)

    if blocks is not None:
        if not isinstance(model, nn.Module):
            raise TypeError(f"blocks= needs an nn.Module, got {type(model).__name__}")
        return Target(denoiser=model, sites=discover_sites(model, blocks), description="user blocks")
    for _, adapt in model_adapters():
        target = adapt(model)
        if target is not None:
            return target
    if isinstance(model, nn.Module):
        return Target(denoiser=model, sites=discover_sites(model), description=type(model).__name__)
    raise TypeError(
        f"tts.accelerate expects an nn.Module, a Diffusion Policy policy or a diffusers pipeline; "
        f"got {type(model).__name__}"
    )


def accelerate(
    model: Any,
    directions: Iterable[str] = ("forward", "timestep", "rollout"),
    *,
    plan: Optional[Plan] = None,
    sparsity: Optional[float] = None,
    pruner: Optional[PrunerModule] = None,
    parallel: Union[bool, str] = "auto",
    blocks: BlocksArg = None,
    fast_dense: bool = True,
    forecast: int = 0,
    fuse_steps: bool = True,
) -> Accelerator:
    """Install test-time sparsity on ``model`` and return the :class:`Accelerator`.

    directions: any subset of ``("forward", "timestep", "rollout")``.
    plan: a :class:`tts.plans.Plan`; default dense (outputs bit-identical) or, with ``sparsity``,
        ``plans.uniform(sparsity, "timestep")`` (FORA-style evenly spread full steps).
    sparsity: target fraction of reused (step, branch) decisions, in [0, 1). With ``pruner``, it
        switches the pruner to exact-budget mode (that many decisions reuse, ranked by the pruner).
    pruner: a trained :class:`tts.Pruner` or :class:`tts.StaticRouter` (:mod:`tts.policy_training`):
        decisions per sample and call, predicted from the model's condition memory (argmax, as in the paper, unless
        ``sparsity`` is given). It is moved to the model's device (it reads the model's condition memory).
    parallel: run the pruner on a side CUDA stream (GPU) / worker thread (CPU) while step 0 runs;
        ``"auto"``: on CPU only when torch leaves a core idle (see :class:`tts.PrunerPlan`).
    blocks: ``{glob over module names: BlockSpec}`` for blocks tts does not recognise.
    forecast: order O of a TaylorSeer-style forecast for timestep reuse (0: reuse the cached output
        as is; 1: extrapolate linearly from the last two computes; ...).
    fast_dense: when a block computes every branch for every sample and nothing needs caching,
        call the block's own forward (keeps PyTorch fast paths, bit-identical outputs).
    fuse_steps: when every branch of a step reuses (timestep or rollout) for every sample, and the
        adapter declares its blocks a residual chain (DiT, pre-norm DP-T), run the step's blocks as one
        add of the summed cached outputs (same result up to float summation order).
    """
    dirs = check_directions(directions)
    if pruner is not None:
        if plan is not None:
            raise ValueError("give either plan= or pruner=, not both")
        missing = [d for d in pruner.config.directions if d not in dirs]
        if missing:
            raise ValueError(f"the pruner reuses along {missing}, which is not in directions={dirs}")
        weights = next(model.parameters(), None) if isinstance(model, nn.Module) else None
        if weights is not None:
            pruner.to(weights.device)
        plan = PrunerPlan(pruner, mode="argmax" if sparsity is None else "budget", sparsity=sparsity,
                          parallel=parallel)
        sparsity = None
    if sparsity is not None:
        sparsity = check_sparsity(sparsity)
        if plan is not None:
            raise ValueError("give either plan= or sparsity= (which builds a uniform plan), not both")
    target = resolve_target(model, blocks)
    if "rollout" in dirs and target.supports_rollout is False:
        raise ValueError(
            f"{target.description or type(model).__name__} is not used in rollouts (it is an image "
            "generator), so the 'rollout' direction does not apply: use "
            "directions=('forward', 'timestep')"
        )
    if plan is None:
        if sparsity is None or sparsity == 0.0:
            plan = plans.dense()
        else:
            if not dirs:
                raise ValueError("sparsity > 0 needs at least one direction to reuse from")
            plan = plans.uniform(sparsity, "timestep" if "timestep" in dirs else dirs[0])
    return Accelerator(target, dirs, plan, fast_dense=fast_dense, forecast=forecast, fuse_steps=fuse_steps)
