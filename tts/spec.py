"""Declarations of what a residual branch is, and how backbones are recognised.

A *branch* is one residual term ``h = h + f(h, ...)`` of a transformer block (self-attention,
cross-attention, MLP; for adaLN blocks the gated term ``gate * f(modulate(norm(h)))``), in the sense
of PyTorch's ``nn.TransformerDecoderLayer._sa_block / _mha_block / _ff_block``.

A :class:`BlockSpec` tells the engine how to run one block branch by branch: its ``forward`` is a
re-statement of the block's own forward in which every residual term goes through ``run``::

    def forward(block, run, x, c):
        x = x + run(0, lambda h: block.attn(block.norm1(h)), x)
        x = x + run(1, lambda h: block.mlp(block.norm2(h)), x)
        return x

``run(i, fn, *batched)`` returns the branch delta: ``fn(*batched)`` when the branch is computed, or a
cached delta when it is reused. Arguments in ``batched`` are per-sample (row-selected when only some
samples of the batch compute); everything shared across the batch (masks, modules) is captured by the
closure. A :class:`Lazy` argument is evaluated at most once per block call, and only if some branch
of the block computes (used for adaLN modulation).

Whole-step fusion: when a block is a pure sum of its branches (``BlockSpec.residual``: its forward
is exactly ``x + run(0, ...) + run(1, ...) + ...`` with ``x`` its first argument) and the blocks
form one chain on the residual stream (``Target.chain``), a step at which every branch of every
block reuses the timestep or rollout cache is the input plus a sum of cached tensors; the engine
then adds that sum once at the first block and passes the stream through the others (no per-branch
work, and the per-order sums of a forecast are kept between computes). Where the adapter also
gives ``Target.skip_blocks``, such a step does not enter the blocks at all: the denoiser's input
embedding, the sum, and its output head.

Backbone knowledge lives in ``tts.adapters``; the core only keeps the registries below.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence

import torch.nn as nn

__all__ = [
    "BranchSpec",
    "BlockSpec",
    "Lazy",
    "Target",
    "register_block_family",
    "register_model_adapter",
    "block_families",
    "model_adapters",
]


@dataclass(frozen=True)
class BranchSpec:
    """One residual branch of a block.

    name: label shown in summaries (``"self_attn"``).
    kind: branch type; the *forward* direction reuses the latest computed branch of the same kind.
    modules: attribute paths of the block's submodules that only this branch uses (FLOPs attribution).
    probe: optional, for self-attention branches: ``probe(fn, block, *args) -> (delta, received)`` runs
        the branch (``fn(*args)``, same output) and also returns the attention each token receives
        [B, N] (mean over heads and queries). Token-refresh plans with attention scores (ToCa,
        :mod:`tts.tokens`) ask for it at full-compute steps.
    """

    name: str
    kind: str
    modules: tuple[str, ...] = ()
    probe: Optional[Callable[..., Any]] = None


@dataclass(frozen=True)
class BlockSpec:
    """How to run one block branch by branch. See the module docstring."""

    family: str
    branches: tuple[BranchSpec, ...]
    forward: Callable[..., Any]
    batch_dim: int = 0
    residual: bool = False  # forward(block, run, x, ...) == x + sum of the branch deltas, nothing else

    def __post_init__(self) -> None:
        if not self.branches:
            raise ValueError(f"BlockSpec {self.family!r} declares no branches")


class Lazy:
    """A per-block value computed on first use (e.g. adaLN modulation chunks), at most once."""

    __slots__ = ("_fn", "_value", "_done")

    def __init__(self, fn: Callable[[], Any]):
        self._fn = fn
        self._done = False
        self._value = None

    def __call__(self) -> Any:
        if not self._done:
            self._value = self._fn()
            self._done = True
        return self._value


def _first_tensor_batch(args: tuple, kwargs: dict) -> int:
    import torch

    for a in list(args) + list(kwargs.values()):
        if isinstance(a, torch.Tensor) and a.dim() > 0:
            return int(a.shape[0])
    raise ValueError("cannot infer the batch size: the denoiser was called without tensor arguments")


def _default_timestep(args: tuple, kwargs: dict) -> Any:
    for key in ("timestep", "timesteps", "t"):
        if key in kwargs:
            return kwargs[key]
    if len(args) > 1:
        return args[1]
    return None


@dataclass
class Target:
    """What ``tts.accelerate`` acts on, as resolved by a model adapter.

    denoiser: module whose forward is one denoising step (the step counter hooks it).
    sites: (qualified name, block module, spec) for every block with prunable branches.
    boundaries: (object, method name) pairs; each call of such a method starts a new sampling call
        (``predict_action``). Without boundaries, a new call is detected from the timestep argument.
    episode_resets: (object, method name) pairs that end an episode (``reset``): clears the rollout cache.
    supports_rollout: False for models that are never used in rollouts (image generators).
    condition: (object, method name) of the function that encodes the condition for all K steps of
        a call at once ([B, K, Tc, D]); its output is what a learned pruner reads (DP-T:
        ``model.condition_memory``).
    condition_of: ``(args, kwargs) -> [B, K, Tc, D]``, the condition memory of the call that a
        denoiser forward with these arguments starts; for sampling loops that never call a
        ``condition`` function (Diffusion Policy's own loop encodes the condition inside every
        forward). Used at step 0 of a call for which no ``condition`` call was seen.
    condition_note: why the adapter could declare neither, shown when a plan needs the condition.
    chain: the sites run one after another on one residual stream with nothing in between
        (``for blk in blocks: x = blk(x, ...)``, x the first positional argument). With every
        site's ``BlockSpec.residual``, whole-step reuse is fused (see the module docstring).
    skip_blocks: ``(args, kwargs, delta) -> output``, optional with ``chain``: the denoiser's output for
        these arguments when the whole chain of blocks is replaced by adding ``delta`` to the stream
        that enters the first block (what the blocks of a fused step amount to). A fused step then
        runs only the model's input embedding and output head, none of its block machinery.
    timers: (object, method name, key) of work a sampling call does before its denoising loop (an
        image encoder): the seconds spent in each go into that call's ``timing[key]``.
    """

    denoiser: nn.Module
    sites: list[tuple[str, nn.Module, BlockSpec]]
    boundaries: list[tuple[Any, str]] = field(default_factory=list)
    episode_resets: list[tuple[Any, str]] = field(default_factory=list)
    supports_rollout: Optional[bool] = None
    condition: Optional[tuple[Any, str]] = None
    condition_of: Optional[Callable[[tuple, dict], Any]] = None
    condition_note: str = ""
    timestep_of: Callable[[tuple, dict], Any] = _default_timestep
    batch_of: Callable[[tuple, dict], int] = _first_tensor_batch
    description: str = ""
    chain: bool = False
    skip_blocks: Optional[Callable[[tuple, dict, Any], Any]] = None
    timers: list[tuple[Any, str, str]] = field(default_factory=list)


BlockMatcher = Callable[[nn.Module], Optional[BlockSpec]]
ModelAdapter = Callable[[Any], Optional[Target]]

_BLOCK_FAMILIES: list[tuple[str, BlockMatcher]] = []
_MODEL_ADAPTERS: list[tuple[str, ModelAdapter]] = []


def register_block_family(name: str, match: BlockMatcher) -> None:
    """Register a function that returns a :class:`BlockSpec` for blocks of one family, else None."""
    _BLOCK_FAMILIES[:] = [(n, m) for n, m in _BLOCK_FAMILIES if n != name] + [(name, match)]


def register_model_adapter(name: str, adapt: ModelAdapter) -> None:
    """Register a function that resolves a whole model/policy into a :class:`Target`, else None."""
    _MODEL_ADAPTERS[:] = [(n, m) for n, m in _MODEL_ADAPTERS if n != name] + [(name, adapt)]


def block_families() -> Sequence[tuple[str, BlockMatcher]]:
    """The registered (name, matcher) block families, in registration order."""
    return tuple(_BLOCK_FAMILIES)


def model_adapters() -> Sequence[tuple[str, ModelAdapter]]:
    """The registered (name, adapter) model adapters, tried in registration order."""
    return tuple(_MODEL_ADAPTERS)
