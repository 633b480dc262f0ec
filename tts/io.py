"""Atomic file writes (results and checkpoints are never left half-written by an interruption), the
weights + config file pair of a checkpoint, and the name of the device a job runs on (provenance)."""
from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path
from typing import Iterator, Union

__all__ = ["atomic_path", "checkpoint_pair", "device_name", "processor_name"]


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


def processor_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :func:`platform.processor` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def device_name(device: Union[str, "torch.device"]) -> str:
    """``"cpu: <model>"`` or ``"cuda: <GPU name>"`` for a torch device (where a training stretch ran)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    return f"{device.type}: {processor_name()}" if device.type == "cpu" else device.type
