"""The accelerator: branch hooks, step tracking, real skipping, per-sample gather/scatter.

Hot path per branch (``Accelerator._run``): one list lookup of the step's decision; compute calls the
branch and stores references in the caches, reuse returns a cached tensor. Decisions are turned into
that fast form once per step (plans live on the host, so there is no device sync per branch). When
the samples of a batch disagree on a branch, only the computing rows are gathered and run, and the
delta is scattered back together with the reused rows (``_run_mixed``).
"""
from __future__ import annotations

import fnmatch
import functools
import time
from dataclasses import dataclass
from typing import Any, Callable, Hashable, Mapping, Optional, Sequence, Union

import torch
import torch.nn as nn

from .cache import ReuseCache
from .flops import MacProfiler
from .hooks import Patches
from .plans import COMPUTE, DIRECTIONS, ROLLOUT, TIMESTEP, TOKENS, Plan
from .spec import BlockSpec, Lazy, Target, block_families
from .summary import CallRecord, Summary

__all__ = ["Accelerator", "discover_sites"]


@dataclass
class _Site:
    name: str
    module: nn.Module
    spec: BlockSpec
    base: int  # global index of the block's first branch
    original: Callable = None  # the block's own forward
    runner: Callable = None


def discover_sites(
    root: nn.Module, blocks: Optional[Mapping[str, Union[BlockSpec, Callable[[nn.Module], BlockSpec]]]] = None
) -> list[tuple[str, nn.Module, BlockSpec]]:
    """Find the blocks of ``root``: by the registered families, or by ``{glob: spec}`` if given."""
    sites: list[tuple[str, nn.Module, BlockSpec]] = []
    matched: list[str] = []

    def inside_matched(name: str) -> bool:
        return any(name.startswith(m + ".") for m in matched)

    for name, module in root.named_modules():
        if not name and blocks is None:
            continue
        if inside_matched(name):
            continue
        spec = None
        if blocks is not None:
            for pattern, s in blocks.items():
                if fnmatch.fnmatchcase(name, pattern):
                    spec = s if isinstance(s, BlockSpec) else s(module)
                    break
        else:
            for _, match in block_families():
                spec = match(module)
                if spec is not None:
                    break
        if spec is not None:
            sites.append((name, module, spec))
            matched.append(name)
    if not sites:
        if blocks is not None:
            raise ValueError(
                f"no module of {type(root).__name__} matches the block patterns {list(blocks)}; "
                "patterns are globs over names from model.named_modules(), e.g. 'blocks.*'"
            )
        families = ", ".join(n for n, _ in block_families())
        raise TypeError(
            f"tts found no recognisable transformer block in {type(root).__name__}. Recognised "
            f"families: {families}. Declare your block with a BlockSpec: "
            "tts.accelerate(model, blocks={'path.to.blocks.*': tts.BlockSpec(...)}) "
            "(see docs/custom_blocks.md)."
        )
    return sites


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


def _call_probe(probe: Callable, module: nn.Module, fn: Callable, *args: Any) -> tuple:
    return probe(fn, module, *args)


class Accelerator:
    """Installed by :func:`tts.accelerate`. See the README for the user-facing API."""

    def __init__(self, target: Target, directions: Sequence[str], plan: Plan, fast_dense: bool = True,
                 forecast: int = 0, fuse_steps: bool = True):
        self.target = target
        self.directions = tuple(directions)
        self.plan = plan
        self.fast_dense = fast_dense
        self.use_rollout = "rollout" in self.directions

        self.sites: list[_Site] = []
        kinds: list[str] = []
        kind_of_branch: list[int] = []
        self.branch_names: list[str] = []
        self.branch_kinds: list[str] = []
        self._batch_dim: list[int] = []
        self._site_of: list[int] = []
        self._probe: list[Optional[Callable]] = []
        for name, module, spec in target.sites:
            site = _Site(name, module, spec, base=len(kind_of_branch))
            for br in spec.branches:
                self._site_of.append(len(self.sites))
                self._probe.append(None if br.probe is None else functools.partial(_call_probe, br.probe, module))
                if br.kind not in kinds:
                    kinds.append(br.kind)
                kind_of_branch.append(kinds.index(br.kind))
                self.branch_names.append(f"{name}.{br.name}")
                self.branch_kinds.append(br.kind)
                self._batch_dim.append(spec.batch_dim)
            self.sites.append(site)
        self.num_branches = len(kind_of_branch)
        # whole-step fusion (tts.spec): one add per step where every branch reuses T or R
        self.fuse_steps = bool(fuse_steps and target.chain and all(s.spec.residual for s in self.sites))
        if forecast and "timestep" not in self.directions:
            raise ValueError("forecast= applies to the timestep direction, which is not enabled")
        self.cache = ReuseCache(kind_of_branch, len(kinds), self.directions, forecast=forecast,
                                batch_dims=self._batch_dim)
        self.plan.bind(self.num_branches, self.branch_kinds)
        allowed = {COMPUTE} | {DIRECTIONS[d] for d in self.directions}
        if TOKENS in self.plan.uses:
            self._check_token_plan()
            allowed.add(TOKENS)
        bad = sorted(set(self.plan.uses) - allowed)
        if bad:
            names = [n for n, c in DIRECTIONS.items() if c in bad]
            raise ValueError(
                f"plan {self.plan.describe()} reuses along {names}, which is not in "
                f"directions={self.directions}"
            )
        self._owner_of = self._build_owners()

        # runtime state
        self._k = 0
        self._in_step = False
        self._batch: Optional[int] = None
        self._explicit = bool(target.boundaries)
        self._pending_call = True
        self._t0: Optional[float] = None
        self._t_prev = 0.0
        self._tdir = 0.0
        self._episode_dense = self.use_rollout
        self._episode_batch: Optional[int] = None
        self._dense_call = False
        self._store = False
        self._row: list[int] = []
        self._groups: dict[int, tuple] = {}
        self._passthrough = True
        self._fused = False  # this step is fused
        self._fuse_pending = False  # ... and its sum has not been added yet
        self._memo: dict[int, tuple] = {}
        self._all_compute = torch.zeros(1, self.num_branches, dtype=torch.int8)
        self._profile_key: Optional[tuple] = None
        self._soft: Optional[torch.Tensor] = None  # [B, nb, O] straight-through gates (training)
        self._soft_codes: list[int] = list(getattr(plan, "codes", []))
        self._timing: dict[str, float] = {}
        self._want_probe = False
        self._device = torch.device("cpu")  # of the current call's inputs
        self.macs_per_row: Optional[dict[Hashable, float]] = None
        self.calls: list[CallRecord] = []
        self.max_records = 1000
        self.removed = False

        self._patches = Patches(self)
        try:
            self._install()
        except BaseException:
            self._patches.restore()  # never leave a model half-patched
            raise

    def _check_token_plan(self) -> None:
        """A token-refresh plan (code TOKENS) needs the timestep cache, tokens on dim 1, and
        attention probes when it scores tokens by attention."""
        if "timestep" not in self.directions:
            raise ValueError(f"plan {self.plan.describe()} refreshes tokens into the timestep cache: "
                             "enable the 'timestep' direction")
        if self.cache.forecast:
            raise ValueError("forecast= and token-wise refresh do not combine (the refreshed tokens have no "
                             "derivative history)")
        if any(d != 0 for d in self._batch_dim):
            raise ValueError("token-wise refresh needs blocks with batch on dim 0 and tokens on dim 1")
        if getattr(self.plan, "wants_probe", False):
            attn = [n for n, kd, p in zip(self.branch_names, self.branch_kinds, self._probe)
                    if "attn" in kd and p is None]
            if attn or not any(p is not None for p in self._probe):
                raise ValueError(f"plan {self.plan.describe()} scores tokens by attention, but the block family "
                                 f"declares no attention probe (BranchSpec.probe) for {attn[:3] or 'any branch'}; "
                                 "use a score that needs no attention maps (tts.tokens.duca)")

    # ------------------------------------------------------------------ install / remove
    def _build_owners(self) -> dict[nn.Module, Hashable]:
        owner: dict[nn.Module, Hashable] = {}
        for si, site in enumerate(self.sites):
            for m in site.module.modules():
                owner[m] = ("shared", si)
            for bi, br in enumerate(site.spec.branches):
                for path in br.modules:
                    sub = site.module.get_submodule(path)
                    for m in sub.modules():
                        owner[m] = ("branch", site.base + bi)
        return owner

    def _install(self) -> None:
        for site in self.sites:
            site.runner = functools.partial(self._run, site.base)

            def make_block(orig, site=site):
                site.original = orig

                def forward(*args, **kwargs):
                    if self._passthrough or not self._in_step:
                        return orig(*args, **kwargs)
                    if self._fused:
                        return self._fused_block(site, args)
                    return site.spec.forward(site.module, site.runner, *args, **kwargs)

                return forward

            self._patches.patch(site.module, "forward", make_block)

        def make_denoiser(orig):
            def forward(*args, **kwargs):
                return self._step(orig, args, kwargs)

            return forward

        self._patches.patch(self.target.denoiser, "forward", make_denoiser)

        def make_boundary(orig):
            def call(*args, **kwargs):
                self._pending_call = True
                before = self.calls[-1] if self.calls else None
                t0 = time.perf_counter()
                try:
                    return orig(*args, **kwargs)
                finally:
                    if self.calls and self.calls[-1] is not before:  # this call reached the denoiser
                        self.calls[-1].timing["total"] = time.perf_counter() - t0

            return call

        def make_condition(orig):
            def call(*args, **kwargs):
                t0 = time.perf_counter()
                memory = orig(*args, **kwargs)
                self._timing = {"encoder": time.perf_counter() - t0}
                observe = getattr(self.plan, "observe", None)
                if observe is not None and not self.removed:
                    observe(memory, dense=self._episode_dense)
                return memory

            return call

        if self.target.condition is not None:
            self._patches.patch(*self.target.condition, make_condition)
        elif getattr(self.plan, "observe", None) is not None:
            raise ValueError(
                f"{self.plan.describe()} reads the condition memory, but the adapter of "
                f"{self.target.description or type(self.target.denoiser).__name__} declares no "
                "Target.condition (the function that encodes the condition for all steps)"
            )

        def make_reset(orig):
            def call(*args, **kwargs):
                self.new_rollout()
                return orig(*args, **kwargs)

            return call

        for obj, name in self.target.boundaries:
            self._patches.patch(obj, name, make_boundary)
        for obj, name in self.target.episode_resets:
            self._patches.patch(obj, name, make_reset)

    def remove(self) -> None:
        """Undo every patch; the model is exactly as before. Safe to call twice."""
        self._patches.restore()
        self.cache.begin_call()
        self.cache.new_episode()
        self.removed = True

    def __enter__(self) -> "Accelerator":
        return self

    def __exit__(self, *exc) -> None:
        self.remove()

    # ------------------------------------------------------------------ public controls
    def new_rollout(self) -> None:
        """Episode boundary: clear the rollout cache; the next call runs dense to refill it."""
        self.cache.new_episode()
        self._episode_dense = self.use_rollout
        self._episode_batch = None

    def new_call(self) -> None:
        """Mark the next denoiser forward as step 0 of a new sampling call (explicit mode)."""
        self._explicit = True
        self._pending_call = True

    @property
    def step_index(self) -> int:
        """Index of the next denoising step within the current call."""
        return self._k

    def summary(self) -> Summary:
        """Decisions, realised sparsity and MACs of the recorded calls."""
        return Summary(
            branch_names=list(self.branch_names),
            calls=list(self.calls),
            macs_per_row=self.macs_per_row,
            num_sites=len(self.sites),
            site_of_branch=[si for si, s in enumerate(self.sites) for _ in s.spec.branches],
            plan=self.plan.describe(),
            directions=self.directions,
        )

    # ------------------------------------------------------------------ step tracking
    def _is_new_call(self, args: tuple, kwargs: dict) -> bool:
        if self._explicit:
            return self._pending_call
        t = self.target.timestep_of(args, kwargs)
        if t is None:
            raise ValueError(
                "tts cannot tell where a sampling call starts: the denoiser was called without a "
                "timestep argument. Call acc.new_call() before each sampling call."
            )
        t = float(t.reshape(-1)[0]) if isinstance(t, torch.Tensor) else float(t)
        # Timesteps move monotonically within a call (down for DDPM/DDIM, up for some flow
        # samplers); a step that does not continue that motion starts a new call.
        if self._t0 is None or self._k == 0:
            new = True
        elif self._k == 1:
            new = t == self._t0
            self._tdir = 0.0 if new else (1.0 if t > self._t0 else -1.0)
        else:
            new = (t - self._t_prev) * self._tdir <= 0
        if new:
            self._t0 = t
        self._t_prev = t
        return new

    def _step(self, orig: Callable, args: tuple, kwargs: dict) -> Any:
        if self.removed:
            return orig(*args, **kwargs)
        batch = self.target.batch_of(args, kwargs)
        if self._is_new_call(args, kwargs) or self._batch is None:
            self._start_call(batch, args, kwargs)
        elif batch != self._batch:
            raise ValueError(
                f"batch size changed from {self._batch} to {batch} inside a sampling call "
                f"(step {self._k}); call acc.new_call() when starting a new call"
            )
        self._prepare_step(self._k, batch)
        if self._k == 0:
            self._maybe_profile(orig, args, kwargs, batch)
        self._in_step = True
        t0 = time.perf_counter()
        try:
            out = orig(*args, **kwargs)
        finally:
            self._in_step = False
        timing = self.calls[-1].timing
        timing["decoder"] = timing.get("decoder", 0.0) + time.perf_counter() - t0
        self._k += 1
        return out

    def _start_call(self, batch: int, args: tuple = (), kwargs: Optional[dict] = None) -> None:
        self._device = next((a.device for a in list(args) + list((kwargs or {}).values())
                             if isinstance(a, torch.Tensor)), torch.device("cpu"))
        self._pending_call = False
        self._k = 0
        if self.use_rollout and not self._episode_dense and batch != self._episode_batch:
            raise ValueError(
                f"batch size changed from {self._episode_batch} to {batch} within a rollout "
                "episode; the rollout cache is per sample. Call acc.new_rollout() (or the "
                "policy's reset()) when the set of environments changes."
            )
        self.cache.begin_call()
        self._dense_call = self._episode_dense
        if self._dense_call:
            self.cache.new_episode()
            self._episode_dense = False
            self._episode_batch = batch
        self._batch = batch
        self._store = self.plan.may_reuse
        self._want_probe = bool(getattr(self.plan, "wants_probe", False))
        self.plan.begin_call(len(self.calls), batch)
        if len(self.calls) >= self.max_records:
            self.calls.pop(0)
        record = CallRecord(batch=batch, dense=self._dense_call, timing=dict(self._timing))
        self._timing = {}
        if not self._dense_call:
            record.pruner_macs = getattr(self.plan, "macs_per_sample", 0.0) * batch
        self.calls.append(record)

    def _prepare_step(self, k: int, batch: int) -> None:
        self._soft = None
        self._fused = self._fuse_pending = False
        if getattr(self.plan, "soft", False) and k > 0 and not self._dense_call:
            self._prepare_soft(k)
            return
        if k == 0 or self._dense_call:
            rows = self._all_compute
        else:
            rows = self.plan.step(k, batch)
            if self.use_rollout and not self.cache.rollout_ready(k):
                miss = rows == ROLLOUT
                if bool(miss.any()):
                    self.calls[-1].fallbacks += int(miss.sum()) * (batch if rows.shape[0] == 1 else 1)
                    rows = rows.masked_fill(miss, COMPUTE)
        if k == 1:  # the pruner (if any) has finished: record its time and the wait for it
            self.calls[-1].timing.update(getattr(self.plan, "timing", {}))
        self.calls[-1].steps.append(rows)
        memo = self._memo.get(id(rows))
        if memo is None or memo[0] is not rows:
            memo = (rows,) + self._fast_form(rows, batch)
            if len(self._memo) > 4096:
                self._memo.clear()
            self._memo[id(rows)] = memo
        _, self._row, self._groups, all_compute, all_reuse = memo
        self._passthrough = self.fast_dense and all_compute and not self._store
        self._fused = self._fuse_pending = (self.fuse_steps and all_reuse and k > 0 and not self._dense_call
                                            and not self._want_probe)
        if self._fused:
            self.calls[-1].fused_steps += 1

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
        self.calls[-1].steps.append(table[g.detach().argmax(-1).cpu()])
        self._passthrough = False

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

    def _maybe_profile(self, orig: Callable, args: tuple, kwargs: dict, batch: int) -> None:
        """Count MACs per branch once per input-shape signature, in a separate dense dry run.

        Module hooks switch off some fused PyTorch kernels, so the counted step is not the real one:
        the real step runs afterwards without hooks (outputs stay bit-identical). Costs one extra
        dense step per new input shape.
        """
        key = tuple(
            tuple(a.shape) for a in list(args) + list(kwargs.values()) if isinstance(a, torch.Tensor)
        )
        if key == self._profile_key:
            return
        self._profile_key = key
        profiler = MacProfiler(self.target.denoiser, self._owner_of, [s.module for s in self.sites])
        with profiler, torch.no_grad():
            orig(*args, **kwargs)  # block wrappers pass through: _in_step is False
        self.macs_per_row = {owner: v / batch for owner, v in profiler.totals.items()}

    # ------------------------------------------------------------------ branch execution
    def _fused_block(self, site: _Site, args: tuple) -> torch.Tensor:
        """A block of a fused step: the first adds every branch's reused output, the rest pass x on."""
        if not args or not isinstance(args[0], torch.Tensor):
            raise RuntimeError(f"block {site.name} was called without its residual stream as first positional "
                               "argument, which Target.chain promises; build the Target with chain=False")
        x = args[0]
        if not self._fuse_pending:
            return x
        self._fuse_pending = False
        return x + self.cache.step_total(self._row, self._k)

    def _run(self, base: int, i: int, fn: Callable, *batched: Any) -> torch.Tensor:
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
                self.cache.write(b, self._k, d)
            return d
        if code == TOKENS:
            return self._run_tokens(b, fn, batched)
        if code > 0:
            cached = self.cache.read(code, b, self._k)
            if cached is None:
                raise RuntimeError(f"internal: empty {code} cache for branch {self.branch_names[b]}")
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
        cidx, reuse = self._on_device(b, self._device)
        dim = self._batch_dim[b]
        batch = self._batch
        out = None
        if cidx is not None:
            d = fn(*[_select_rows(a, dim, cidx, batch) for a in batched])
            shape = list(d.shape)
            shape[dim] = batch
            out = d.new_empty(shape)
            out.index_copy_(dim, cidx, d)
        for code, idx in reuse:
            src = self.cache.read(code, b, self._k)
            if out is None:
                out = torch.empty_like(src)
            out.index_copy_(dim, idx, src.index_select(dim, idx))
        if cidx is not None and self._store:
            self.cache.write_rows(b, self._k, cidx, d, dim)
        return out

    def _run_tokens(self, b: int, fn: Callable, batched: tuple) -> torch.Tensor:
        """Recompute the plan's chosen tokens of branch b, keep the cached output for the others."""
        cached = self.cache.read(TIMESTEP, b, self._k)
        if cached is None:
            raise RuntimeError(f"internal: empty timestep cache for branch {self.branch_names[b]}")
        B, N = cached.shape[0], cached.shape[1]
        idx = self.plan.select_tokens(b, self._site_of[b], self._k, cached)  # [B, m]

        def pick(a: Any) -> Any:
            if type(a) is Lazy:
                a = a()
            if isinstance(a, torch.Tensor) and a.dim() >= 3 and a.shape[0] == B and a.shape[1] == N:
                return a.gather(1, idx.view(B, -1, *([1] * (a.dim() - 2))).expand(-1, -1, *a.shape[2:]))
            return a

        d = fn(*[pick(a) for a in batched])
        out = cached.scatter(1, idx.view(B, -1, *([1] * (d.dim() - 2))).expand_as(d), d)
        self.cache.write(b, self._k, out)
        work = self.calls[-1].token_work
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
            cached = self.cache.read(code, b, self._k)
            if cached is not None:
                out = out + g[:, j].reshape(shape).to(d.dtype) * cached
        computed = g[:, 0].detach() > 0.5
        if bool(computed.all()):
            self.cache.write(b, self._k, d.detach())
        elif bool(computed.any()):
            rows = computed.nonzero().flatten()
            self.cache.write_rows(b, self._k, rows, d.detach().index_select(dim, rows), dim)
        return out
