"""Atomic file writes (results and checkpoints are never left half-written by an interruption), and
the weights + config file pair of a checkpoint."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "checkpoint_pair"]


@contextlib.contextmanager
def atomic_path(path: Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` if the block succeeds.
    ``suffix`` ends the temporary name (for writers that append one, e.g. ``np.savez``'s ``.npz``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def checkpoint_pair(path: Path) -> tuple[Path, Path]:
    """(``<path>.safetensors``, ``<path>.json``). The suffixes are appended, so names with dots
    (``lift_0.93``) keep them; a path given with either suffix names the same pair."""
    path = Path(path)
    if path.suffix in (".json", ".safetensors"):
        path = path.with_suffix("")
    return path.with_name(path.name + ".safetensors"), path.with_name(path.name + ".json")
