"""The accelerator: installs test-time sparsity on a model and ties its parts together.

- :mod:`tts.calls` (:class:`~tts.calls.CallTracker`): which denoiser forward starts a sampling call,
  the step index, episode boundaries, batch-size checks.
- :mod:`tts.execution` (:class:`~tts.execution.BranchExecutor`): each step's decisions applied
  branch by branch (compute, reuse, per-sample mixed, token-wise, soft gates, fused steps).
- :mod:`tts.cache` (:class:`~tts.cache.ReuseCache`): the forward / timestep / rollout caches.
- here: block discovery, the reversible patches (denoiser, blocks, call boundaries, condition
  encoder, episode resets), MAC profiling and the record of every call (:meth:`Accelerator.summary`).
"""
from __future__ import annotations

import fnmatch
import functools
import time
import warnings
from typing import Any, Callable, Hashable, Mapping, Optional, Sequence, Union

import torch
import torch.nn as nn

from .cache import ReuseCache
from .calls import CallTracker
from .execution import BranchExecutor, BranchLayout, Site
from .flops import MacProfiler
from .hooks import Patches
from .plans import COMPUTE, DIRECTIONS, TOKENS, Plan
from .spec import BlockSpec, Target, block_families
from .summary import CallRecord, Summary

__all__ = ["Accelerator", "discover_sites"]


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


def _first_device(args: tuple, kwargs: dict) -> torch.device:
    return next((a.device for a in list(args) + list(kwargs.values()) if isinstance(a, torch.Tensor)),
                torch.device("cpu"))


class Accelerator:
    """Test-time sparsity installed on one model; returned by :func:`tts.accelerate`.

    The model is patched in place (reversibly): its denoiser counts steps, its blocks run branch by
    branch as the plan decides. :meth:`remove` (or leaving a ``with`` block) restores it exactly.
    Sampling calls are found from the timestep argument, from the adapter's boundary methods
    (``predict_action``) or from :meth:`new_call`; episodes end at the adapter's reset methods or
    :meth:`new_rollout`. :meth:`summary` reports decisions, realised sparsity, MACs and timing.
    """

    def __init__(self, target: Target, directions: Sequence[str], plan: Plan, fast_dense: bool = True,
                 forecast: int = 0, fuse_steps: bool = True):
        self.target = target
        self.directions = tuple(directions)
        self.plan = plan
        self.use_rollout = "rollout" in self.directions
        layout = BranchLayout.from_sites(target.sites)
        self.sites: list[Site] = layout.sites
        self.branch_names: list[str] = layout.names
        self.branch_kinds: list[str] = layout.kinds
        self.num_branches = len(layout)
        self._layout = layout
        # whole-step fusion (see tts.spec): one add per step where every branch reuses T or R
        self.fuse_steps = bool(fuse_steps and target.chain and all(s.spec.residual for s in self.sites))
        self._skip_blocks = target.skip_blocks if self.fuse_steps else None
        if forecast and "timestep" not in self.directions:
            raise ValueError("forecast= applies to the timestep direction, which is not enabled")
        self.cache = ReuseCache(layout.kind_index, layout.num_kinds, self.directions, forecast=forecast,
                                batch_dims=layout.batch_dims)
        self._bind_plan()
        self.tracker = CallTracker(target, self.use_rollout)
        self.executor = BranchExecutor(layout, self.cache, plan, use_rollout=self.use_rollout,
                                       fast_dense=fast_dense, fuse_steps=self.fuse_steps)
        self.calls: list[CallRecord] = []
        self.calls_started = 0  # every sampling call so far (self.calls keeps the last max_records)
        self.max_records = 1000
        self.macs_per_row: Optional[dict[Hashable, float]] = None
        self.removed = False
        self._owner_of = self._build_owners()
        self._profile_key: Optional[tuple] = None
        self._timing: dict[str, float] = {}  # of the call about to start (condition encoder)
        self._observed = False  # the plan has seen the condition memory of the call about to start
        self._warned_length = False
        # the condition memory from the denoiser's step-0 inputs, for loops that encode no condition up front
        self._condition_of = target.condition_of if plan.reads_condition else None

        self._patches = Patches(self)
        try:
            self._install()
        except BaseException:
            self._patches.restore()  # never leave a model half-patched
            raise

    # ------------------------------------------------------------------ plan checks
    def _bind_plan(self) -> None:
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

    def _check_token_plan(self) -> None:
        """A token-refresh plan (code TOKENS) needs the timestep cache, tokens on dim 1, and
        attention probes when it scores tokens by attention."""
        layout = self._layout
        if "timestep" not in self.directions:
            raise ValueError(f"plan {self.plan.describe()} refreshes tokens into the timestep cache: "
                             "enable the 'timestep' direction")
        if self.cache.forecast:
            raise ValueError("forecast= and token-wise refresh do not combine (the refreshed tokens have no "
                             "derivative history)")
        if any(d != 0 for d in layout.batch_dims):
            raise ValueError("token-wise refresh needs blocks with batch on dim 0 and tokens on dim 1")
        if self.plan.wants_probe:
            attn = [n for n, kd, p in zip(layout.names, layout.kinds, layout.probes) if "attn" in kd and p is None]
            if attn or not any(p is not None for p in layout.probes):
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
        ex = self.executor
        for site in self.sites:
            site.runner = functools.partial(ex.run, site.base)

            def make_block(orig, site=site):
                def forward(*args, **kwargs):
                    if ex.passthrough or not ex.in_step:
                        return orig(*args, **kwargs)
                    if ex.fused:
                        return ex.fused_block(site, args)
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
                self.tracker.mark_call()
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
                self._timing["encoder"] = time.perf_counter() - t0
                if self.plan.reads_condition and not self.removed:
                    self.plan.observe(memory, dense=self.tracker.episode_dense)
                    self._observed = True
                return memory

            return call

        if self.target.condition is not None:
            self._patches.patch(*self.target.condition, make_condition)
        elif self.plan.reads_condition and self.target.condition_of is None:
            raise ValueError(
                f"{self.plan.describe()} reads the condition memory, but the adapter of "
                f"{self.target.description or type(self.target.denoiser).__name__} declares no "
                "Target.condition (the function that encodes the condition for all steps)"
                + (f": {self.target.condition_note}" if self.target.condition_note else "")
            )

        def make_timer(orig, key):
            def call(*args, **kwargs):
                t0 = time.perf_counter()
                try:
                    return orig(*args, **kwargs)
                finally:
                    self._timing[key] = self._timing.get(key, 0.0) + time.perf_counter() - t0

            return call

        for obj, name, key in self.target.timers:
            self._patches.patch(obj, name, functools.partial(make_timer, key=key))

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

    def __exit__(self, *exc: Any) -> None:
        self.remove()

    # ------------------------------------------------------------------ public controls
    def new_rollout(self) -> None:
        """Episode boundary: clear the rollout cache; the next call runs dense to refill it."""
        self.cache.new_episode()
        self.tracker.new_episode()

    def new_call(self) -> None:
        """Mark the next denoiser forward as step 0 of a new sampling call (explicit mode: from now
        on calls start only where marked, not by timestep motion)."""
        self.tracker.mark_call(explicit=True)

    @property
    def step_index(self) -> int:
        """Index of the next denoising step within the current call (0 after ``new_call()``; where
        calls are found by timestep motion, a forward whose timestep starts a new call is step 0)."""
        return 0 if self.tracker.pending else self.tracker.k

    def summary(self) -> Summary:
        """Decisions, realised sparsity and MACs of the recorded calls."""
        self._check_call_length()
        return Summary(
            branch_names=list(self.branch_names),
            calls=list(self.calls),
            macs_per_row=self.macs_per_row,
            num_sites=len(self.sites),
            site_of_branch=list(self._layout.site_of),
            plan=self.plan.describe(),
            directions=self.directions,
            timer_keys=[key for _, _, key in self.target.timers],
        )

    # ------------------------------------------------------------------ one denoising step
    def _step(self, orig: Callable, args: tuple, kwargs: dict) -> Any:
        if self.removed:
            return orig(*args, **kwargs)
        tracker, ex = self.tracker, self.executor
        t_enter = time.perf_counter()
        if tracker.begin_step(args, kwargs):
            self._start_call(args, kwargs)
        k = tracker.k
        record = self.calls[-1]
        ex.prepare_step(k)
        if k == 1:  # the pruner (if any) has finished: record its time and the wait for it
            record.timing.update(self.plan.timing)
        elif k == 0:
            self._maybe_profile(orig, args, kwargs, tracker.batch)
        ex.in_step = True
        timing = record.timing
        t0 = time.perf_counter()
        skip = ex.fused and self._skip_blocks is not None
        try:
            if skip:
                ex.fused = ex._fuse_pending = False
                out = self._skip_blocks(args, kwargs, self.cache.step_total(ex._row, k))
            else:
                out = orig(*args, **kwargs)
        finally:
            ex.in_step = False
        t1 = time.perf_counter()
        timing["decoder"] = timing.get("decoder", 0.0) + t1 - t0
        if skip:
            timing["reuse_steps"] = timing.get("reuse_steps", 0.0) + t1 - t0
        if k > 1:  # steps 0 and 1 also start the call (MAC profile) and wait for the pruner ("wait")
            timing["engine"] = timing.get("engine", 0.0) + t0 - t_enter
        tracker.end_step()
        return out

    def _start_call(self, args: tuple, kwargs: dict) -> None:
        """Step 0 of a new sampling call: fresh per-call caches, the plan told, a new record."""
        tracker = self.tracker
        batch, dense = tracker.batch, tracker.dense_call
        self._check_call_length()
        self.cache.begin_call()
        if dense:
            self.cache.new_episode()
        if self._condition_of is not None and not self._observed:
            t0 = time.perf_counter()
            memory = self._condition_of(args, kwargs)
            self._timing["encoder"] = time.perf_counter() - t0
            self.plan.observe(memory, dense=dense)
        self._observed = False
        self.plan.begin_call(self.calls_started, batch)
        self.calls_started += 1
        if len(self.calls) >= self.max_records:
            self.calls.pop(0)
        record = CallRecord(batch=batch, dense=dense, timing=self._timing)
        self._timing = {}
        if not dense:
            record.pruner_macs = self.plan.macs_per_sample * batch
        self.calls.append(record)
        self.executor.begin_call(record, batch, _first_device(args, kwargs), dense)

    def _check_call_length(self) -> None:
        """Warn (once) when the call that just ended ran fewer steps than the plan was made for: a
        schedule or pruner made for another sampler would otherwise apply only its first rows."""
        want = self.plan.num_steps
        if want is None or not self.calls or self._warned_length:
            return
        ran = len(self.calls[-1].steps)
        if ran < want:
            self._warned_length = True
            warnings.warn(f"{self.plan.describe()} was made for {want} denoising steps but a sampling call ran {ran}: "
                          "only its first rows applied (run the sampler it was made for, e.g. file:S+ddim:K)",
                          stacklevel=4)

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
            orig(*args, **kwargs)  # block wrappers pass through: the executor is not in a step
        self.macs_per_row = {owner: v / batch for owner, v in profiler.totals.items()}
