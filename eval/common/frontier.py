"""Score against policy-call speed: the frontier of every method of a policy (eval/tables.py,
eval/figures.py).

The score is success, or for a policy whose runs record goal coverage (Push-T) the mean best
coverage per episode, from eval/robot.py runs on the test seeds (validation runs never pool), pooled
per method; speed is the method's speed-up over dense in eval/frontier_latency.py, where every
method was timed against the same dense reference in one process. A point is on the frontier when no
other point is at least as fast and scores at least as high (one of them strictly). A sparse method
beats fewer steps when its score is significantly higher (paired 95% interval above zero, on the
same episodes) than the best fewer-step sampler that is at least as fast, where up to 5% slower
counts as as fast (latency medians move that much between runs).

Images (:func:`image_frontier_points`): the score is the FID of an eval/imagenet.py run (lower is
better) with its bootstrap interval over the samples, the speed against dense DDIM-50 from one
eval/image_latency.py file. FID intervals are not paired, so a sparse method beats fewer steps only
when the difference interval built from both intervals (its low end minus the sampler's high end,
and the reverse) lies below zero: a conservative test.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from .methods import SAMPLERS
from .stats import mean_interval, newcombe_paired, paired_counts, paired_score_difference, policy_of, pooled, wilson

__all__ = ["Point", "family", "frontier_points", "image_frontier_points", "on_frontier", "beats_fewer_steps",
           "is_win", "untimed_samplers", "FEW_STEP", "SAMPLER_FAMILIES"]

FEW_STEP = re.compile(rf"({'|'.join(SAMPLERS)}):(\d+)(?::(\w+))?$")
# the fewer-step samplers: each sampler with its default timestep spacing, then its other spacings
SAMPLER_FAMILIES = (*SAMPLERS, *(f"{name}-{s}" for name, spacings in SAMPLERS.items() for s in spacings[1:]))


def family(method: str) -> str:
    """dense | ddim | ddim-trailing | dpm | ddpm (fewer-step samplers) | sparse (every engine method)."""
    if method == "dense":
        return "dense"
    m = FEW_STEP.match(method)
    if m:
        name, spacing = m.group(1), m.group(3)
        return name if spacing is None or spacing == SAMPLERS[name][0] else f"{name}-{spacing}"
    return "sparse"


@dataclass
class Point:
    """One method of one policy at one batch size: its ``score`` (``metric``: "success" or "coverage")
    with a 95% interval."""

    method: str
    score: float
    episodes: int
    interval: tuple[float, float]
    speedup: float
    latency_ms: float
    computed_steps: int
    runs: list[dict] = field(repr=False, default_factory=list)
    metric: str = "success"

    @property
    def family(self) -> str:
        return family(self.method)

    @property
    def lower_is_better(self) -> bool:
        return self.metric == "fid"

    def at_least_as_good(self, other: "Point") -> bool:
        return self.score <= other.score if self.lower_is_better else self.score >= other.score


def _success_runs(folder: Path, policy: str) -> dict[str, list[dict]]:
    runs: dict[str, list[dict]] = {}
    for path in sorted(folder.glob("*.json")):
        if path.name.startswith(("frontier_latency_", "latency_")):
            continue
        r = json.loads(path.read_text())
        if "success_rate" in r and r["episodes_done"] == r["episodes_requested"] and policy_of(r) == policy:
            runs.setdefault(r["method"], []).append(r)
    return runs


def frontier_points(folder: Path, policy: str, batch: int, latency_folder: Optional[Path] = None) -> list[Point]:
    """The methods of ``policy`` (as :func:`policy_of` names it) with both test-seed success runs and a
    latency row at ``batch`` in ``frontier_latency_<policy>.json``; dense included (speed-up 1). The
    latency file is read from ``latency_folder`` (default ``folder``; e.g. the rows timed on a GPU)."""
    slug = policy.replace(" (", "-").rstrip(")")
    lat_path = (latency_folder or folder) / f"frontier_latency_{slug}.json"
    if not lat_path.exists():
        return []
    rows = {r["method"]: r for r in json.loads(lat_path.read_text())["rows"] if r["batch"] == batch}
    if not rows:
        return []
    dense_ms = next(iter(rows.values()))["dense_ms"]
    rows["dense"] = {"latency_ms": dense_ms, "speedup": 1.0, "computed_steps": -1}
    points = []
    runs = _success_runs(folder, policy)
    coverage = any(r.get("mean_max_coverage") is not None for rs in runs.values() for r in rs)
    for method, rs in runs.items():
        lat = rows.get(method)
        if lat is None:
            continue
        n = sum(r["episodes_done"] for r in rs)
        if coverage:
            mean, lo, hi = mean_interval([e["max_coverage"] for r in rs for e in r["episodes"]])
            score, interval = mean, (max(lo, 0.0), min(hi, 1.0))
        else:
            k = round(pooled(rs)[0] * n)
            score, interval = k / n, wilson(k, n)
        points.append(Point(method, score, n, interval, lat["speedup"], lat["latency_ms"], lat["computed_steps"], rs,
                            "coverage" if coverage else "success"))
    return sorted(points, key=lambda p: p.speedup)


def image_frontier_points(folder: Path, latency: Path, batch: int) -> list[Point]:
    """The image methods with a finished FID run in ``folder`` (``digits_*.json``) and a row at ``batch``
    in ``latency`` (eval/image_latency.py output); dense included (speed-up 1). Score: FID."""
    if not latency.exists():
        return []
    rows = [r for r in json.loads(latency.read_text())["rows"] if r["batch"] == batch]
    if not rows:
        return []
    lat = dict(rows[0]["methods"], dense={"ms": rows[0]["dense_ms"], "speedup": 1.0})
    points = []
    for path in sorted(folder.glob("digits_*.json")):
        r = json.loads(path.read_text())
        method = r.get("method")
        if r.get("fid") is None or method not in lat:
            continue
        lo, hi = r.get("fid_interval") or (float("nan"), float("nan"))
        points.append(Point(method, r["fid"], r["num_samples"], (lo, hi), lat[method]["speedup"], lat[method]["ms"],
                            r["steps"], [r], "fid"))
    return sorted(points, key=lambda p: p.speedup)


def on_frontier(p: Point, points: list[Point]) -> bool:
    """No other point is at least as fast and scores as well, and strictly better in one of them."""
    return not any(q is not p and q.speedup >= p.speedup and q.at_least_as_good(p)
                   and (q.speedup > p.speedup or q.score != p.score) for q in points)


def untimed_samplers(folder: Path, policy: str, points: list[Point]) -> dict[str, int]:
    """The fewer-step samplers of ``policy`` with finished test-seed runs in ``folder`` but no latency
    row among ``points``, with their step counts. A sparse call's win over the timed samplers is no
    verdict while one of these takes at most as many steps as it computes (it would likely be as fast)."""
    timed = {q.method for q in points}
    steps = {m: int(FEW_STEP.match(m).group(2)) for m in _success_runs(folder, policy)
             if family(m) in SAMPLER_FAMILIES and m not in timed}
    return dict(sorted(steps.items(), key=lambda item: (family(item[0]), item[1])))


# Latency medians move by a few percent between runs of the same method: a sampler up to this much
# slower than a sparse method still counts as "as fast" in its verdict (the verdict gets harder to win)
AS_FAST_TOLERANCE = 0.05


def is_win(p: Point, verdict: tuple[Point, float, float, float]) -> bool:
    """Whether :func:`beats_fewer_steps`'s ``verdict`` on ``p`` is significant in ``p``'s favour."""
    return verdict[3] < 0 if p.lower_is_better else verdict[2] > 0


def beats_fewer_steps(p: Point, points: list[Point]) -> Optional[tuple[Point, float, float, float]]:
    """The best fewer-step sampler at least as fast as ``p`` (within :data:`AS_FAST_TOLERANCE`) and the
    paired difference p - it with its 95% interval, or None when no such sampler was run. ``p`` beats fewer steps when the lower bound
    is above zero (for FID, lower is better: when the upper bound is below zero)."""
    rivals = [q for q in points if q.family in SAMPLER_FAMILIES
              and q.speedup >= p.speedup * (1 - AS_FAST_TOLERANCE)]
    if not rivals:
        return None
    if p.lower_is_better:  # FID: unpaired intervals, combined conservatively
        best = min(rivals, key=lambda q: (q.score, -q.speedup))
        return best, p.score - best.score, p.interval[0] - best.interval[1], p.interval[1] - best.interval[0]
    best = max(rivals, key=lambda q: (q.score, q.speedup))
    if p.metric == "coverage":
        d = paired_score_difference(p.runs, best.runs)
        return None if d is None else (best, *d[:3])
    diff, lo, hi = newcombe_paired(*paired_counts(p.runs, best.runs))
    return best, diff, lo, hi
