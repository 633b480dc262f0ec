"""Command-line options of the pruner trainers (eval/train_pruner.py, eval/train_image_pruner.py):
each option is the field of the same name of :class:`tts.training.PrunerTrainingConfig` (the
trainers add ``--n-train`` / ``--n-val`` with their own defaults)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, TypeVar

import tts
from common import provenance
from tts.training import PRECISIONS, TrainingStopped

__all__ = ["STOPPED_STATUS", "add_training_args", "exit_when_stopped", "training_metadata"]

STOPPED_STATUS = 3  # exit status of a trainer stopped on request (its state saved; --resume continues it)
T = TypeVar("T")


def add_training_args(ap: argparse.ArgumentParser, *, sparsity: float, directions: str, batch: int) -> None:
    ap.add_argument("--out", type=Path, required=True, help="pruner path without suffix")
    ap.add_argument("--directions", default=directions)
    ap.add_argument("--sparsity", type=float, default=sparsity)
    ap.add_argument("--lam", type=float, default=1.0, help="weight of the sparsity term")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--batch", type=int, default=batch)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--weight-decay", type=float, default=1e-4)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--forecast", type=int, default=0,
                    help="train (and validate) with TaylorSeer-style forecasting timestep reuse of this order; "
                         "use the same --forecast at test time")
    ap.add_argument("--prior", type=Path, default=None,  # a schedule JSON, or every_n:N
                    help="a searched static schedule (eval/search_static.py JSON) whose decisions become fixed "
                         "prior logits; the pruner (head zero-initialised) learns per-sample corrections")
    ap.add_argument("--prior-reuse", default=None, choices=sorted(tts.plans.DIRECTIONS),
                    help="map every reuse decision of --prior to this direction (single-direction variants "
                         "of a searched schedule, e.g. its compute steps with rollout reuse in between)")
    ap.add_argument("--train-budget", action="store_true",
                    help="training gates take the exact-budget decision (top 1 - sparsity by compute "
                         "probability) in the forward: sparsity fixed, the pruner learns the ranking")
    ap.add_argument("--prior-margin", type=float, default=3.0,
                    help="logit of the prior's option (smaller: the pruner can move away from it sooner)")
    ap.add_argument("--tie-branches", action="store_true",
                    help="one decision per step for all branches (step-level pruner; use with a step-level prior)")
    ap.add_argument("--step-query", action="store_true",
                    help="with --tie-branches: one decoder query per step instead of one per branch "
                         "(the same decisions' shape at ~1/num_branches of the decoder's MACs)")
    ap.add_argument("--val-mode", choices=["argmax", "budget"], default="argmax",
                    help="test-time rule used for validation and checkpoint selection (budget: exactly --sparsity)")
    ap.add_argument("--heads", type=int, default=4, help="attention heads of the pruner's decoder layer")
    ap.add_argument("--ffn", type=int, default=128, help="feed-forward width of the pruner's decoder layer")
    ap.add_argument("--lr-schedule", choices=["cosine", "linear"], default="cosine",
                    help="per epoch: warm-up over the first fifth, then cosine or linear decay")
    ap.add_argument("--clip-grad", type=_clip, default=1.0, help="gradient-norm clip, or 'none'")
    ap.add_argument("--precision", choices=sorted(PRECISIONS), default="float32",
                    help="the pruner's forward/backward in training: float32, or bfloat16 autocast (mixed "
                         "precision: about 2x faster on CPUs with avx512_bf16 / amx_bf16, about 25x slower on CPUs "
                         "without them, where it is emulated); a resumed run may change it (recorded)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")


def _clip(text: str):
    return None if text.lower() == "none" else float(text)


def training_metadata(args: argparse.Namespace) -> dict:
    """The checkpoint metadata a trainer's command line contributes: provenance, then every option
    as given (paths as strings)."""
    meta = provenance(seeds={"train": args.seed})
    meta.update({k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()})
    return meta


def exit_when_stopped(train: Callable[[], T]) -> T:
    """``train()``; a run stopped on request (the STOP file in its run directory,
    :class:`tts.training.TrainingStopped`) ends the process with its message and exit status
    :data:`STOPPED_STATUS`, so that a script does not take it for a finished training."""
    try:
        return train()
    except TrainingStopped as e:
        print(e, file=sys.stderr)
        raise SystemExit(STOPPED_STATUS) from None
