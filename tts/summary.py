"""What an accelerator did: decisions per (step, sample, branch), realised sparsity and MACs."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Hashable, Optional, Sequence

import torch

from .flops import OTHER
from .plans import CODE_NAMES, COMPUTE, ROLLOUT, TOKENS

__all__ = ["CallRecord", "Summary"]

_LETTER = "CFTRP"  # P: partial (token-wise refresh)


@dataclass
class CallRecord:
    """Decisions applied in one sampling call: ``steps[k]`` is int8 [1 or batch, num_branches]."""

    batch: int
    dense: bool = False
    steps: list[torch.Tensor] = field(default_factory=list)
    fallbacks: int = 0
    # seconds: encoder, pruner, wait, decoder (every step's denoiser forward; reuse_steps: the part spent in
    # fused steps that skip the blocks), engine (per-step bookkeeping from step 2 on), total
    timing: dict[str, float] = field(default_factory=dict)
    pruner_macs: float = 0.0  # MACs of the pruner in this call (whole batch)
    token_work: dict[int, float] = field(default_factory=dict)  # branch -> sum of token fractions refreshed
    fused_steps: int = 0  # steps run as one add of cached outputs (every branch reused, see tts.spec)

    def decisions(self) -> torch.Tensor:
        """[steps, batch, num_branches] int8."""
        if not self.steps:
            return torch.zeros(0, self.batch, 0, dtype=torch.int8)
        return torch.stack([s.expand(self.batch, -1) for s in self.steps])


@dataclass
class Summary:
    """The recorded calls of an accelerator with its branch layout (``Accelerator.summary()``);
    ``str(summary)`` is a readable report, :meth:`to_dict` a JSON-ready one."""

    branch_names: list[str]
    calls: list[CallRecord]
    macs_per_row: Optional[dict[Hashable, float]]
    num_sites: int
    site_of_branch: list[int]
    plan: str
    directions: Sequence[str]
    timer_keys: Sequence[str] = ()  # work timed before the denoising loop (e.g. an image encoder)

    # ---------------------------------------------------------------- numbers
    @staticmethod
    def sparsity_of(call: CallRecord) -> float:
        """Fraction of one call's (step, sample, branch) decisions that reused."""
        d = call.decisions()
        return float((d != COMPUTE).float().mean()) if d.numel() else 0.0

    def sparsity(self, calls: Optional[Sequence[CallRecord]] = None) -> float:
        """Fraction of (step, sample, branch) decisions that reused, over ``calls`` (default all)."""
        calls = self.calls if calls is None else calls
        total = sum(c.decisions().numel() for c in calls)
        reused = sum(int((c.decisions() != COMPUTE).sum()) for c in calls)
        return reused / total if total else 0.0

    def counts(self, calls: Optional[Sequence[CallRecord]] = None) -> dict[str, int]:
        """Number of decisions per code name (compute, forward, ...) over ``calls`` (default all)."""
        calls = self.calls if calls is None else calls
        out = {name: 0 for name in CODE_NAMES}
        for c in calls:
            d = c.decisions()
            for code, name in enumerate(CODE_NAMES):
                out[name] += int((d == code).sum())
        return out

    def rollout_ages(self, calls: Optional[Sequence[CallRecord]] = None) -> torch.Tensor:
        """Age in calls of every reused rollout slot: for each rollout decision at (call, sample, step,
        branch), how many calls ago that (step, branch) was last computed for that sample (1: the
        previous call's output). The rollout cache writes a slot only when it computes, so a static
        rollout schedule reuses the episode's first call ever older features. ``calls`` must be
        consecutive calls (default: all recorded); slots whose last compute precedes the first of
        them are left out. Returns a 1-D long tensor (empty without rollout reuse)."""
        calls = self.calls if calls is None else list(calls)
        ages: list[torch.Tensor] = []
        last: Optional[torch.Tensor] = None  # [K, B, nb] index of the call that last computed the slot, -1 unknown
        for i, call in enumerate(calls):
            d = call.decisions()
            if call.dense or last is None or last.shape != d.shape:
                last = torch.full(d.shape, -1, dtype=torch.long)
            reused = (d == ROLLOUT) & (last >= 0)
            if bool(reused.any()):
                ages.append(i - last[reused])
            last = torch.where(d == COMPUTE, torch.full_like(last, i), last)
        return torch.cat(ages) if ages else torch.zeros(0, dtype=torch.long)

    def rollout_age_stats(self, calls: Optional[Sequence[CallRecord]] = None) -> dict:
        """Mean, median, max and the fraction of age 1 (previous-call features) of :meth:`rollout_ages`."""
        a = self.rollout_ages(calls)
        if not a.numel():
            return {"reused_slots": 0}
        return {"reused_slots": int(a.numel()), "mean_calls": float(a.float().mean()),
                "median_calls": float(a.float().median()), "max_calls": int(a.max()),
                "fraction_previous_call": float((a == 1).float().mean())}

    def macs(self, call: CallRecord) -> tuple[float, float]:
        """(dense, realised) MACs of one call, from the profiled per-row MACs."""
        if self.macs_per_row is None:
            return float("nan"), float("nan")
        m = self.macs_per_row
        branch = torch.tensor([m.get(("branch", b), 0.0) for b in range(len(self.branch_names))], dtype=torch.float64)
        shared = torch.tensor([m.get(("shared", s), 0.0) for s in range(self.num_sites)], dtype=torch.float64)
        other = m.get(OTHER, 0.0)
        d = call.decisions()  # [K, B, nb]
        K, B = d.shape[0], d.shape[1]
        dense = K * B * (other + float(branch.sum()) + float(shared.sum()))
        computed = (d == COMPUTE).to(torch.float64)  # [K, B, nb]
        realised = K * B * other + float((computed.sum(1) * branch).sum())
        # token-wise refresh: the refreshed fraction of the branch's tokens, for the whole batch
        realised += B * sum(frac * float(branch[b]) for b, frac in call.token_work.items())
        # a block's shared part runs (for the whole batch) when any of its branches computes
        site = torch.tensor(self.site_of_branch)
        site_active = torch.zeros(K, self.num_sites, dtype=torch.float64)
        site_active.index_add_(1, site, ((d == COMPUTE) | (d == TOKENS)).to(torch.float64).amax(1))
        realised += float(((site_active > 0).to(torch.float64) * shared).sum()) * B
        return dense, realised

    def timing(self, calls: Optional[Sequence[CallRecord]] = None) -> dict[str, float]:
        """Median seconds per call of each recorded phase (encoder, pruner, wait, decoder, reuse_steps
        (part of decoder), engine, the adapter's timers such as image_encoder, scheduler_and_rest, total) over ``calls`` (default: the calls that were not dense first calls of an episode)."""
        calls = [c for c in self.calls if not c.dense] if calls is None else calls
        rows = []
        for c in calls:
            t = dict(c.timing)
            if "total" in t:  # the sampling loop outside the denoiser: scheduler steps, normalisation, noise
                # ("wait" holds the pruner's time the sampling thread spent on it: all of it when it
                # ran in that thread, the part step 0 did not cover when it overlapped)
                parts = ("encoder", "wait", "decoder", "engine", *self.timer_keys)
                t["scheduler_and_rest"] = t["total"] - sum(t.get(k, 0.0) for k in parts)
            rows.append(t)
        keys = sorted({k for t in rows for k in t})
        return {k: float(torch.tensor([t[k] for t in rows if k in t]).median()) for k in keys}

    def to_dict(self) -> dict:
        """Sparsity, decision counts, timing and the last call's MACs, JSON-ready."""
        last = self.calls[-1] if self.calls else None
        sparse_calls = [c for c in self.calls if not c.dense]
        out = {
            "plan": self.plan,
            "directions": list(self.directions),
            "num_branches": len(self.branch_names),
            "calls": len(self.calls),
            "sparsity_all_calls": self.sparsity(),
            "sparsity_non_dense_calls": self.sparsity(sparse_calls),
            "decision_counts": self.counts(),
            "timing_median_s": self.timing(),
        }
        if "rollout" in self.directions:
            out["rollout_age"] = self.rollout_age_stats()
        if last is not None:
            dense, realised = self.macs(last)
            out.update(
                last_call={
                    "batch": last.batch,
                    "steps": len(last.steps),
                    "dense_first_call": last.dense,
                    "sparsity": self.sparsity_of(last),
                    "rollout_fallbacks": last.fallbacks,
                    "macs_dense": dense,
                    "macs_realised": realised,
                    "macs_pruner": last.pruner_macs,
                    "macs_realised_with_pruner": realised + last.pruner_macs,
                }
            )
        return out

    # ---------------------------------------------------------------- text
    def grid(self, call: Optional[CallRecord] = None, sample: int = 0) -> str:
        """One line per step, one letter per branch: C compute, F/T/R reuse direction."""
        call = call or (self.calls[-1] if self.calls else None)
        if call is None:
            return "(no calls recorded)"
        d = call.decisions()[:, sample]
        lines = [f"{k:4d} " + "".join(_LETTER[c] for c in row.tolist()) for k, row in enumerate(d)]
        return "\n".join(lines)

    def __str__(self) -> str:
        if not self.calls:
            return f"tts: plan={self.plan} directions={tuple(self.directions)}; no sampling call recorded yet"
        last = self.calls[-1]
        dense, realised = self.macs(last)
        counts = self.counts()
        total = max(sum(counts.values()), 1)
        lines = [
            f"tts: plan={self.plan} directions={tuple(self.directions)}",
            f"  branches: {len(self.branch_names)} ({len(self.branch_names) // max(self.num_sites, 1)} per block x {self.num_sites} blocks)",
            f"  calls recorded: {len(self.calls)}; last call: batch {last.batch}, {len(last.steps)} steps"
            + (", dense (first call of an episode)" if last.dense else ""),
            f"  realised sparsity: last call {self.sparsity_of(last):.1%}, all calls {self.sparsity():.1%}",
            "  decisions (all calls): "
            + ", ".join(f"{k} {v / total:.1%}" for k, v in counts.items()),
        ]
        if last.fallbacks:
            lines.append(f"  rollout cache missing at {last.fallbacks} decisions: computed instead")
        age = self.rollout_age_stats() if "rollout" in self.directions else {"reused_slots": 0}
        if age["reused_slots"]:
            lines.append(f"  rollout reuse: features {age['mean_calls']:.1f} calls old on average (max "
                         f"{age['max_calls']}); {age['fraction_previous_call']:.0%} from the previous call")
        if dense == dense:  # not NaN
            lines.append(
                f"  MACs last call: dense {dense / 1e9:.3f} G, realised {realised / 1e9:.3f} G "
                f"({dense / max(realised, 1):.2f}x fewer)"
            )
            if last.pruner_macs:
                total_macs = realised + last.pruner_macs
                lines.append(f"  with the pruner ({last.pruner_macs / 1e9:.3f} G): {total_macs / 1e9:.3f} G "
                             f"({dense / max(total_macs, 1):.2f}x fewer)")
        timing = self.timing()
        if timing:
            lines.append("  median time per call (ms, non-dense calls; pruner overlaps step 0, wait = "
                         "time step 1 waited for it): "
                         + ", ".join(f"{k} {v * 1e3:.2f}" for k, v in timing.items()))
        d = last.decisions()
        frac = (d == COMPUTE).float().mean((0, 1))
        width = max(len(n) for n in self.branch_names)
        lines.append("  compute fraction per branch (last call):")
        for name, f in zip(self.branch_names, frac.tolist()):
            lines.append(f"    {name:<{width}}  {f:6.1%}")
        lines.append("  decisions per step, sample 0 (C compute, F forward, T timestep, R rollout, "
                     "P token-wise partial refresh):")
        lines.append(self.grid(last))
        return "\n".join(lines)
