"""Provenance and atomic result files shared by the eval scripts."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from tts.io import atomic_path, processor_name

REPO = Path(__file__).resolve().parents[2]


def git_sha() -> str:
    """HEAD of this checkout when this process started, i.e. the code it runs (``-dirty`` with
    uncommitted changes to tracked files); commits made while a long run goes on do not change it.
    ``TTS_GIT_SHA``, when set, wins: a copy of the checkout sent to another machine (e.g. a GPU's) may
    carry no ``.git`` or a stale one, and the sender knows which commit it sent."""
    return os.environ.get("TTS_GIT_SHA") or _SHA_AT_START


def _head() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


_SHA_AT_START = _head()


def machine() -> dict[str, Any]:
    import torch

    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu": processor_name(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "load_average_1_5_15min": list(os.getloadavg()),  # > cpu_count: timings shared the CPU
    }
    return info


def provenance(seeds: Any = None) -> dict[str, Any]:
    return {
        "command": " ".join([Path(sys.executable).name] + sys.argv),
        "git_sha": git_sha(),
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "seeds": seeds,
    }


def parse_args(ap, argv=None):
    """``ap.parse_args(argv)`` with the shared ``--threads`` option applied (torch intra-op threads)."""
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads (use 1 when another job shares the CPU: oversubscribed OpenMP is 20x slower)")
    args = ap.parse_args(argv)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    return args


def add_device_option(ap) -> None:
    """``--device``: where a tool runs the policy (and the model it trains): ``cpu``, ``cuda``, ``cuda:1``."""
    ap.add_argument("--device", default="cpu",
                    help="torch device of the policy (and of what is trained): cpu (default) or cuda[:N]")


def torch_device(name: str):
    """The ``torch.device`` called ``name``; a CUDA device this machine does not have is an error
    (SystemExit with what to do), not a silent fall-back to the CPU."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise SystemExit(f"--device {name!r}: {e}") from None
    if device.type == "cuda" and (not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()):
        raise SystemExit(f"--device {name!r}: this machine has no such CUDA device "
                         f"({torch.cuda.device_count()} visible); use --device cpu")
    if device.type not in ("cpu", "cuda"):
        raise SystemExit(f"--device {name!r}: only cpu and cuda devices are supported")
    return device


def policy_slug(task: str, checkpoint: Any = None) -> str:
    """``task`` for the bundled ``checkpoints/<task>_dpt`` (or no checkpoint), else ``task-<checkpoint
    name>``: result files and figures of different policies never share a name."""
    name = Path(checkpoint).name if checkpoint is not None else f"{task}_dpt"
    return task if name == f"{task}_dpt" else f"{task}-{name}"


def add_replay_options(ap) -> None:
    """``--task``, ``--checkpoint``, ``--trajectories`` and ``--methods``: the options of a tool that
    replays recorded episodes of a policy through one or more methods."""
    from .methods import VOCABULARY

    ap.add_argument("--task", required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--trajectories", type=Path, required=True)
    ap.add_argument("--methods", nargs="+", required=True, help=f"specs of: {VOCABULARY}")


def add_all_episodes_option(ap) -> None:
    """``--all-episodes``: the trajectory tools use every recorded episode, not only the successful ones."""
    ap.add_argument("--all-episodes", action="store_true",
                    help="use every recorded episode, not only the successful ones (for a policy that rarely "
                         "succeeds, e.g. Push-T's, whose episodes run to the horizon)")


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes (hex): which weights a result was produced with."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that an interruption never leaves a half-written file."""
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(text)


def write_json(path: Path, data: Any) -> None:
    write_atomic(path, json.dumps(data, indent=2, sort_keys=False) + "\n")
