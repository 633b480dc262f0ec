"""Test helpers shared by several test files."""
from __future__ import annotations

import torch


def as_tensor(out):
    """Model outputs may be diffusers output objects."""
    return out.sample if hasattr(out, "sample") else out


def run(model, args):
    with torch.no_grad():
        return as_tensor(model(*args)).clone()


def _write_run(folder, task: str, method: str, eps: list, checkpoint: str, prefix: str = "", **extra) -> None:
    """An eval/robot.py result file in ``folder`` for ``eps`` (seed, success and any other fields)."""
    import json
    from pathlib import Path

    doc = {"task": task, "checkpoint": checkpoint, "method": method, "episodes_requested": len(eps),
           "episodes_done": len(eps), "success_rate": sum(e["success"] for e in eps) / len(eps),
           "provenance": {"seeds": [e["seed"] for e in eps]}, "episodes": eps, **extra}
    (Path(folder) / f"{prefix}{method.replace(':', '-')}_{eps[0]['seed']}.json").write_text(json.dumps(doc))


def write_success_run(folder, method: str, successes: list, checkpoint: str = "checkpoints/lift_mh_dpt",
                      first_seed: int = 100000, **extra) -> None:
    """An eval/robot.py result file of a Lift run in ``folder``: one episode per ``successes`` value,
    seeds from ``first_seed``; ``extra`` adds or replaces fields."""
    eps = [{"seed": first_seed + i, "success": bool(x)} for i, x in enumerate(successes)]
    _write_run(folder, "lift", method, eps, checkpoint, **extra)


def write_coverage_run(folder, method: str, coverage: list[float], checkpoint: str = "checkpoints/pusht_mh_dpt_17k",
                       first_seed: int = 100000, **extra) -> None:
    """An eval/robot.py result file of a Push-T run in ``folder``: one episode per ``coverage`` value
    (best goal coverage), seeds from ``first_seed``; ``extra`` adds or replaces fields."""
    eps = [{"seed": first_seed + i, "success": c > 0.95, "max_coverage": c} for i, c in enumerate(coverage)]
    _write_run(folder, "pusht", method, eps, checkpoint, prefix="pusht_",
               **{"mean_max_coverage": sum(coverage) / len(coverage), **extra})
