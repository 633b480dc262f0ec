"""Branch execution: the plan's decisions of one step applied branch by branch.

Hot path per branch (:meth:`BranchExecutor.run`): one list lookup of the step's decision; compute
calls the branch and stores references in the caches, reuse returns a cached tensor. Decisions are
turned into that fast form once per step (plans live on the host, so there is no device sync per
branch). When the samples of a batch disagree on a branch, only the computing rows are gathered and
run, and the delta is scattered back together with the reused rows (``_run_mixed``).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import torch
import torch.nn as nn

from .cache import ReuseCache
from .plans import COMPUTE, ROLLOUT, TIMESTEP, TOKENS, Plan
from .spec import BlockSpec, Lazy
from .summary import CallRecord

__all__ = ["BranchLayout", "BranchExecutor"]


@dataclass
class Site:
    """One block whose branches tts runs: its module, spec and the global index of its first branch."""

    name: str
    module: nn.Module
    spec: BlockSpec
    base: int
    runner: Optional[Callable] = None  # run(i, fn, *batched) for this block's branches


def _call_probe(probe: Callable, module: nn.Module, fn: Callable, *args: Any) -> tuple:
    return probe(fn, module, *args)


@dataclass
class BranchLayout:
    """The branches of a model in execution order (block-major), flattened to global indices."""

    sites: list[Site]
    names: list[str]  # "<block>.<branch>"
    kinds: list[str]
    kind_index: list[int]  # per branch, index into the distinct kinds (forward-direction slots)
    num_kinds: int
    batch_dims: list[int]
    site_of: list[int]
    probes: list[Optional[Callable]]  # probe(fn, *args) -> (delta, attention received) or None

    @classmethod
    def from_sites(cls, sites: Sequence[tuple[str, nn.Module, BlockSpec]]) -> "BranchLayout":
        """The layout of every branch of ``sites`` (name, module, spec), in execution order."""
        layout = cls([], [], [], [], 0, [], [], [])
        kinds: list[str] = []
        for name, module, spec in sites:
            layout.sites.append(Site(name, module, spec, base=len(layout.names)))
            for br in spec.branches:
                if br.kind not in kinds:
                    kinds.append(br.kind)
                layout.names.append(f"{name}.{br.name}")
                layout.kinds.append(br.kind)
                layout.kind_index.append(kinds.index(br.kind))
                layout.batch_dims.append(spec.batch_dim)
                layout.site_of.append(len(layout.sites) - 1)
                layout.probes.append(None if br.probe is None else functools.partial(_call_probe, br.probe, module))
        layout.num_kinds = len(kinds)
        return layout

    def __len__(self) -> int:
        return len(self.names)


def _select_rows(a: Any, dim: int, rows: torch.Tensor, batch: int) -> Any:
    if type(a) is Lazy:
        a = a()
    if isinstance(a, torch.Tensor):
        if a.dim() > dim and a.shape[dim] == batch:
            return a.index_select(dim, rows)
        return a
    if isinstance(a, (tuple, list)):
        return type(a)(_select_rows(x, dim, rows, batch) for x in a)
    return a


class BranchExecutor:
    """Runs every branch of the current step as decided: compute, reuse, mixed, token-wise or soft.

    The block wrappers read three flags per block call: ``in_step`` (a denoising step is running),
    ``passthrough`` (the step computes everything and keeps nothing: call the block's own forward)
    and ``fused`` (every branch reuses T or R: the step is one add, :meth:`fused_block`).
    """

    def __init__(self, layout: BranchLayout, cache: ReuseCache, plan: Plan, *, use_rollout: bool,
                 fast_dense: bool, fuse_steps: bool):
        self.cache = cache
        self.plan = plan
        self.use_rollout = use_rollout
        self.fast_dense = fast_dense
        self.fuse_steps = fuse_steps
        self.names = layout.names
        self._batch_dim = layout.batch_dims
        self._site_of = layout.site_of
        self._probe = layout.probes
        self._soft_codes: list[int] = list(plan.codes)
        self._all_compute = torch.zeros(1, len(layout), dtype=torch.int8)
        self._memo: dict[int, tuple] = {}
        self._forms: dict[tuple, tuple] = {}
        # per call
        self.record: Optional[CallRecord] = None
        self.batch = 0
        self.dense_call = False
        self.device = torch.device("cpu")
        self._store = False
        self._want_probe = False
        # per step
        self.k = 0
        self.in_step = False
        self.passthrough = True
        self.fused = False  # this step is fused ...
        self._fuse_pending = False  # ... and its sum has not been added yet
        self._row: list[int] = []
        self._groups: dict[int, tuple] = {}
        self._soft: Optional[torch.Tensor] = None  # [B, nb, O] straight-through gates (training)

    # ------------------------------------------------------------------ per call / per step
    def begin_call(self, record: CallRecord, batch: int, device: torch.device, dense: bool) -> None:
        """A new sampling call: decisions and branch work go to ``record``; ``dense``: compute everything."""
        self.record = record
        self.batch = batch
        self.device = device
        self.dense_call = dense
        self._store = self.plan.may_reuse
        self._want_probe = self.plan.wants_probe

    def prepare_step(self, k: int) -> None:
        """Turn the plan's decisions for step ``k`` into the per-branch fast form."""
        self.k = k
        batch = self.batch
        record = self.record
        self._soft = None
        self.fused = self._fuse_pending = False
        if self.plan.soft and k > 0 and not self.dense_call:
            self._prepare_soft(k)
            return
        if k == 0 or self.dense_call:
            rows = self._all_compute
        else:
            rows = self.plan.step(k, batch)
            if self.use_rollout and not self.cache.rollout_ready(k):
                miss = rows == ROLLOUT
                if bool(miss.any()):
                    record.fallbacks += int(miss.sum()) * (batch if rows.shape[0] == 1 else 1)
                    rows = rows.masked_fill(miss, COMPUTE)
        record.steps.append(rows)
        memo = self._memo.get(id(rows))
        if memo is None or memo[0] is not rows:
            # a pruner gives a new tensor every step: decision rows equal in content share one form
            key = (tuple(rows.shape), rows.numpy().tobytes()) if rows.device.type == "cpu" else None
            form = self._forms.get(key) if key is not None else None
            if form is None:
                form = self._fast_form(rows, batch)
                if key is not None:
                    if len(self._forms) > 4096:
                        self._forms.clear()
                    self._forms[key] = form
            memo = (rows,) + form
            if len(self._memo) > 4096:
                self._memo.clear()
            self._memo[id(rows)] = memo
        _, self._row, self._groups, all_compute, all_reuse = memo
        self.passthrough = self.fast_dense and all_compute and not self._store
        self.fused = self._fuse_pending = (self.fuse_steps and all_reuse and k > 0 and not self.dense_call
                                           and not self._want_probe)
        if self.fused:
            record.fused_steps += 1

    def _prepare_soft(self, k: int) -> None:
        """Training path: every branch computes; outputs are mixed with straight-through gates."""
        g = self.plan.soft_step(k)
        codes = self._soft_codes
        if self.use_rollout and not self.cache.rollout_ready(k) and ROLLOUT in codes:
            r = codes.index(ROLLOUT)
            g = torch.cat([g[..., :1] + g[..., r:r + 1], g[..., 1:r], torch.zeros_like(g[..., r:r + 1]),
                           g[..., r + 1:]], dim=-1)
        self._soft = g
        table = torch.tensor(codes, dtype=torch.int8)
        self.record.steps.append(table[g.detach().argmax(-1).cpu()])
        self.passthrough = False

    def _fast_form(self, rows: torch.Tensor, batch: int) -> tuple[list[int], dict, bool, bool]:
        """Per branch: one code if all samples agree, else -1 and (compute rows, [(code, rows)]);
        then whether every branch computes, and whether every branch reuses T or R (fusable)."""
        if rows.shape[0] not in (1, batch):
            raise ValueError(f"plan gave decisions for {rows.shape[0]} samples, batch is {batch}")
        row: list[int] = []
        groups: dict[int, tuple] = {}
        for b, col in enumerate(zip(*rows.tolist())):
            first = col[0]
            if all(c == first for c in col):
                row.append(first)
                continue
            row.append(-1)
            where: dict[int, list[int]] = {}
            for i, c in enumerate(col):
                where.setdefault(c, []).append(i)
            cidx = where.pop(COMPUTE, None)
            groups[b] = (
                None if cidx is None else torch.tensor(cidx),
                [(c, torch.tensor(ix)) for c, ix in where.items()],
            )
        all_reuse = not groups and all(c in (TIMESTEP, ROLLOUT) for c in row)
        return row, groups, not any(row) and not groups, all_reuse

    # ------------------------------------------------------------------ branch execution
    def fused_block(self, site: Site, args: tuple) -> torch.Tensor:
        """A block of a fused step: the first adds every branch's reused output, the rest pass x on."""
        if not args or not isinstance(args[0], torch.Tensor):
            raise RuntimeError(f"block {site.name} was called without its residual stream as first positional "
                               "argument, which Target.chain promises; build the Target with chain=False")
        x = args[0]
        if not self._fuse_pending:
            return x
        self._fuse_pending = False
        return x + self.cache.step_total(self._row, self.k)

    def run(self, base: int, i: int, fn: Callable, *batched: Any) -> torch.Tensor:
        """Branch ``i`` of the block whose first branch is ``base``: its delta, computed or reused."""
        b = base + i
        if self._soft is not None:
            return self._run_soft(b, fn, batched)
        code = self._row[b]
        if code == COMPUTE:
            args = [a() if type(a) is Lazy else a for a in batched]
            if self._want_probe and self._probe[b] is not None:
                d, received = self._probe[b](fn, *args)
                self.plan.record_probe(self._site_of[b], received)
            else:
                d = fn(*args)
            if self._store:
                self.cache.write(b, self.k, d)
            return d
        if code == TOKENS:
            return self._run_tokens(b, fn, batched)
        if code > 0:
            cached = self.cache.read(code, b, self.k)
            if cached is None:
                raise RuntimeError(f"internal: empty {code} cache for branch {self.names[b]}")
            return cached
        return self._run_mixed(b, fn, batched)

    def _on_device(self, b: int, device: torch.device) -> tuple:
        """The row indices of branch b's groups on ``device`` (built on the CPU once per decision
        pattern, moved once per pattern: index ops need the index on the data's device)."""
        cidx, reuse = self._groups[b]
        ref = cidx if cidx is not None else reuse[0][1]
        if ref.device != device:
            cidx = None if cidx is None else cidx.to(device)
            reuse = [(c, ix.to(device)) for c, ix in reuse]
            self._groups[b] = (cidx, reuse)
        return cidx, reuse

    def _run_mixed(self, b: int, fn: Callable, batched: tuple) -> torch.Tensor:
        cidx, reuse = self._on_device(b, self.device)
        dim = self._batch_dim[b]
        batch = self.batch
        out = None
        if cidx is not None:
            d = fn(*[_select_rows(a, dim, cidx, batch) for a in batched])
            shape = list(d.shape)
            shape[dim] = batch
            out = d.new_empty(shape)
            out.index_copy_(dim, cidx, d)
        for code, idx in reuse:
            src = self.cache.read(code, b, self.k)
            if out is None:
                out = torch.empty_like(src)
            out.index_copy_(dim, idx, src.index_select(dim, idx))
        if cidx is not None and self._store:
            self.cache.write_rows(b, self.k, cidx, d, dim)
        return out

    def _run_tokens(self, b: int, fn: Callable, batched: tuple) -> torch.Tensor:
        """Recompute the plan's chosen tokens of branch b, keep the cached output for the others."""
        cached = self.cache.read(TIMESTEP, b, self.k)
        if cached is None:
            raise RuntimeError(f"internal: empty timestep cache for branch {self.names[b]}")
        B, N = cached.shape[0], cached.shape[1]
        idx = self.plan.select_tokens(b, self._site_of[b], self.k, cached)  # [B, m]

        def pick(a: Any) -> Any:
            if type(a) is Lazy:
                a = a()
            if isinstance(a, torch.Tensor) and a.dim() >= 3 and a.shape[0] == B and a.shape[1] == N:
                return a.gather(1, idx.view(B, -1, *([1] * (a.dim() - 2))).expand(-1, -1, *a.shape[2:]))
            return a

        d = fn(*[pick(a) for a in batched])
        out = cached.scatter(1, idx.view(B, -1, *([1] * (d.dim() - 2))).expand_as(d), d)
        self.cache.write(b, self.k, out)
        work = self.record.token_work
        work[b] = work.get(b, 0.0) + idx.shape[1] / N
        return out

    def _run_soft(self, b: int, fn: Callable, batched: tuple) -> torch.Tensor:
        d = fn(*[a() if type(a) is Lazy else a for a in batched])
        g = self._soft[:, b]  # [B, O]
        dim = self._batch_dim[b]
        shape = [1] * d.dim()
        shape[dim] = g.shape[0]
        out = g[:, 0].reshape(shape).to(d.dtype) * d
        for j, code in enumerate(self._soft_codes[1:], 1):
            cached = self.cache.read(code, b, self.k)
            if cached is not None:
                out = out + g[:, j].reshape(shape).to(d.dtype) * cached
        computed = g[:, 0].detach() > 0.5
        if bool(computed.all()):
            self.cache.write(b, self.k, d.detach())
        elif bool(computed.any()):
            rows = computed.nonzero().flatten()
            self.cache.write_rows(b, self.k, rows, d.detach().index_select(dim, rows), dim)
        return out
