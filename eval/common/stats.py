"""Pooling and paired statistics of success-rate runs (eval/tables.py, eval/figures.py).

Runs are eval/robot.py result JSONs; episodes with the same environment seed start from the same
initial state, so two methods run on the same seeds are compared pair by pair.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

__all__ = ["VALIDATION_SEEDS", "policy_of", "paired_counts", "paired_success_difference", "wilson", "newcombe_paired",
           "sign_test_p", "mean_interval", "paired_score_difference", "pooled"]

VALIDATION_SEEDS = 400000  # first seeds from here on are validation episodes (recipes/steps_matter.sh)


def policy_of(r: dict) -> str:
    """The task of a run, with its policy when that is not the bundled ``checkpoints/<task>_dpt``, and
    ``, validation`` for runs on validation seeds: runs of different policies or splits never pool."""
    label = r["task"]
    ckpt = Path(r.get("checkpoint", ""))
    if ckpt.name and ckpt.name != f"{r['task']}_dpt":
        label += f" ({ckpt.name})"
    seeds = r.get("provenance", {}).get("seeds") or [0]
    if isinstance(seeds, list) and seeds and seeds[0] >= VALIDATION_SEEDS:
        label += ", validation"
    return label


def pooled(runs: list[dict], key: str = "success_rate") -> tuple[float, int]:
    """A per-run rate (``success_rate``, or ``mean_max_coverage``) pooled over runs, weighted by their
    episodes, and the number of episodes."""
    n = sum(r["episodes_done"] for r in runs)
    return sum(r[key] * r["episodes_done"] for r in runs) / n, n


def paired_counts(runs: list[dict], other: list[dict]) -> tuple[int, int, int, int]:
    """On the episodes both ``runs`` and ``other`` ran (same env seed): both solved, only ``runs``,
    only ``other``, neither."""
    def outcomes(rs):
        return {e["seed"]: bool(e["success"]) for r in rs for e in r["episodes"]}

    mine, ref = outcomes(runs), outcomes(other)
    common = sorted(set(mine) & set(ref))
    both = sum(mine[s] and ref[s] for s in common)
    only_mine = sum(mine[s] and not ref[s] for s in common)
    only_ref = sum(ref[s] and not mine[s] for s in common)
    return both, only_mine, only_ref, len(common) - both - only_mine - only_ref


def paired_success_difference(runs: list[dict], other: list[dict]) -> str:
    """Success difference of ``runs`` to ``other`` (dense, or any baseline) on the episodes both were
    run on (same env seed = same initial state): the paired difference with Newcombe's score interval
    (95%), the discordant counts (only ``other`` / only ``runs`` solved) and the exact two-sided
    sign-test p-value on those counts."""
    both, only_mine, only_ref, neither = paired_counts(runs, other)
    n = both + only_mine + only_ref + neither
    if not n:
        return "no common episodes"
    diff, lo, hi = newcombe_paired(both, only_mine, only_ref, neither)
    return (f"{diff:+.3f} ({_signed(lo)}, {_signed(hi)}) on {n}; {only_ref} / {only_mine}, "
            f"p = {sign_test_p(only_ref, only_mine):.2g}")


def _signed(x: float) -> str:
    """+-x to 3 decimals, or 4 where 3 would print a non-zero bound as 0.000."""
    return f"{x:+.4f}" if 0 < abs(x) < 0.0005 else f"{x:+.3f}"


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion k/n."""
    p, z2 = k / n, z * z
    centre, half = (p + z2 / (2 * n)) / (1 + z2 / n), z * ((p * (1 - p) + z2 / (4 * n)) / n) ** 0.5 / (1 + z2 / n)
    return max(centre - half, 0.0), min(centre + half, 1.0)


def newcombe_paired(a: int, b: int, c: int, d: int, z: float = 1.96) -> tuple[float, float, float]:
    """Difference p1 - p2 of two paired proportions and its confidence interval by Newcombe's (1998,
    Stat. Med. 17:2635) method 10: the Wilson intervals of both margins combined with the
    (continuity-corrected) phi correlation of the 2x2 table. a: both succeed, b: only the first,
    c: only the second, d: neither."""
    n = a + b + c + d
    p1, p2 = (a + b) / n, (a + c) / n
    (l1, u1), (l2, u2) = wilson(a + b, n, z), wilson(a + c, n, z)
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    cross = a * d - b * c
    cross = max(cross - n / 2, 0.0) if cross > 0 else cross  # Newcombe's continuity correction of phi
    phi = cross / margins ** 0.5 if margins else 0.0
    lo = (p1 - p2) - max((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2, 0.0) ** 0.5
    hi = (p1 - p2) + max((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2, 0.0) ** 0.5
    return p1 - p2, max(lo, -1.0), min(hi, 1.0)


def sign_test_p(b: int, c: int) -> float:
    """Exact two-sided sign test (McNemar's exact test) of b vs c discordant pairs."""
    m = b + c
    if m == 0:
        return 1.0
    tail = sum(math.comb(m, k) for k in range(min(b, c) + 1)) / 2 ** m
    return min(1.0, 2 * tail)


def mean_interval(values: list[float]) -> tuple[float, float, float]:
    """Mean of per-episode scores with a 95% normal interval: (mean, low, high); zero width for
    fewer than two values."""
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, mean, mean
    half = 1.96 * (sum((x - mean) ** 2 for x in values) / (n - 1)) ** 0.5 / n ** 0.5
    return mean, mean - half, mean + half


def paired_score_difference(runs: list[dict], other: list[dict], key: str = "max_coverage") -> Optional[tuple[float, float, float, int]]:
    """Mean difference of a per-episode score (``runs`` minus ``other``) on the episodes both ran,
    with a 95% t-interval: (mean, low, high, episodes); None without shared scored episodes."""
    a = {e["seed"]: e[key] for r in runs for e in r["episodes"] if key in e}
    b = {e["seed"]: e[key] for r in other for e in r["episodes"] if key in e}
    d = [a[s] - b[s] for s in a if s in b]
    if len(d) < 2:
        return None
    return (*mean_interval(d), len(d))
