"""Analytic multiply-accumulate (MAC) counts, attributed to branches.

Every module type that does GEMM-like work has a *rule* giving its MACs from the shapes of one call
(``nn.Linear``: out.numel() x in_features; convolutions; ``nn.MultiheadAttention`` with its
projections and the two attention products). Composite attention modules of other libraries register
a rule for the part their child modules do not cover (the QK^T and AV products); adapters do that.

:class:`MacProfiler` hooks these modules during one denoising step and sums MACs per *owner*: a
branch, the shared part of a block (e.g. adaLN modulation, skipped when no branch of the block
computes), or the rest of the model. Element-wise ops, norms and softmax are not counted, the same
convention as ``torch.utils.flop_counter.FlopCounterMode`` (which reports FLOPs = 2 x MACs); the
tests check the two agree on every supported family.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Hashable, Optional, Sequence

import torch.nn as nn

__all__ = ["register_mac_rule", "module_macs", "MacProfiler", "flop_counter_macs", "OTHER"]

MacRule = Callable[[nn.Module, tuple, dict, Any], int]
_RULES: dict[type, MacRule] = {}
OTHER = ("other",)


def register_mac_rule(cls: type, rule: MacRule) -> None:
    """Register ``rule(module, args, kwargs, output) -> MACs`` for modules of type ``cls``."""
    _RULES[cls] = rule


def _rule_for(module: nn.Module) -> Optional[MacRule]:
    for cls in type(module).__mro__:
        rule = _RULES.get(cls)
        if rule is not None:
            return rule
    return None


def module_macs(module: nn.Module, args: tuple, kwargs: dict, output: Any) -> int:
    """MACs of one call of ``module`` (from its inputs and output); 0 for modules without a rule."""
    rule = _rule_for(module)
    return 0 if rule is None else int(rule(module, args, kwargs, output))


def _linear(m: nn.Linear, args, kwargs, out) -> int:
    return out.numel() * m.in_features


def _conv(m: nn.modules.conv._ConvNd, args, kwargs, out) -> int:
    return out.numel() * (m.in_channels // m.groups) * math.prod(m.kernel_size)


def _mha(m: nn.MultiheadAttention, args, kwargs, out) -> int:
    names = ("query", "key", "value")
    q, k, v = (args[i] if i < len(args) else kwargs[n] for i, n in enumerate(names))
    if q.dim() == 2:  # unbatched
        q, k, v = q.unsqueeze(1), k.unsqueeze(1), v.unsqueeze(1)
    elif m.batch_first:
        q, k, v = q.transpose(0, 1), k.transpose(0, 1), v.transpose(0, 1)
    L, N, E = q.shape
    S = k.shape[0]
    proj = N * L * E * E + N * S * k.shape[-1] * E + N * S * v.shape[-1] * E + N * L * E * E
    return proj + 2 * N * L * S * E


register_mac_rule(nn.Linear, _linear)
register_mac_rule(nn.modules.conv._ConvNd, _conv)
register_mac_rule(nn.MultiheadAttention, _mha)


class MacProfiler:
    """Context manager: MACs of every rule-bearing module call inside ``root``, summed per owner.

    A call made while block ``sites[i]`` is running is charged to ``owner_of[module]`` (a branch
    of that block) or to the block's shared part; any other call (even of a module that belongs to
    a block, e.g. DiT reusing ``blocks[0].norm1.emb`` for its final layer) counts under
    :data:`OTHER`.
    """

    def __init__(self, root: nn.Module, owner_of: dict[nn.Module, Hashable], sites: Sequence[nn.Module] = ()):
        self.root = root
        self.owner_of = owner_of
        self.sites = list(sites)
        self.totals: dict[Hashable, int] = {}
        self._handles: list = []
        self._active: list[int] = []

    def _owner(self, module: nn.Module) -> Hashable:
        if not self._active:
            return OTHER
        return self.owner_of.get(module, ("shared", self._active[-1]))

    def __enter__(self) -> "MacProfiler":
        def enter(si: int) -> Callable:
            def pre_hook(*_):
                self._active.append(si)

            return pre_hook

        def leave(*_):
            self._active.pop()

        for si, site in enumerate(self.sites):
            self._handles.append(site.register_forward_pre_hook(enter(si)))
            self._handles.append(site.register_forward_hook(leave))
        for module in self.root.modules():
            if _rule_for(module) is None:
                continue

            def hook(mod, args, kwargs, out):
                owner = self._owner(mod)
                self.totals[owner] = self.totals.get(owner, 0) + module_macs(mod, args, kwargs, out)

            self._handles.append(module.register_forward_hook(hook, with_kwargs=True))
        return self

    def __exit__(self, *exc) -> None:
        for h in self._handles:
            h.remove()
        self._handles.clear()
        self._active.clear()

    @property
    def total(self) -> int:
        """MACs counted over every module."""
        return sum(self.totals.values())


def flop_counter_macs(fn: Callable[[], Any]) -> int:
    """MACs of ``fn()`` as counted by PyTorch's FlopCounterMode (its FLOPs / 2), math attention."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops() // 2
