"""The pruner training loop shared by the robot (eval/train_pruner.py) and image
(eval/train_image_pruner.py) trainers: options, epochs, validation with the test-time rule, best-epoch
selection, resumable state and the checkpoint. The backbone-specific scripts say how one epoch of
training and one validation pass run.

Per epoch: ``train_epoch(opt, rng, noise_rng)`` -> rows ``{"l1", "sparsity", "frames"}``; then
``validate()`` -> the same rows under the test-time rule (``--val-mode``). The score of an epoch is
val L1 + lambda * |val sparsity - target|; the best epoch's weights are written as
``<out>.safetensors/.json`` after every epoch (with the whole history so far), and the full state
under ``runs/<out name>/`` so that ``--resume`` continues.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from common import provenance

import tts
from tts.io import atomic_path
from tts.pruner import PrunerPlan, save_pruner
from tts.static_search import steps_grid

__all__ = ["add_training_args", "fit", "RecordingPlan", "mean_of", "read_grid"]


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
    ap.add_argument("--prior", type=Path, default=None,  # a schedule JSON, or every_n:N (image pruner)
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
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")


def read_grid(path: Path, steps: Optional[int] = None, branches: Optional[int] = None,
              reuse: Optional[str] = None) -> torch.Tensor:
    """The [K, nb] decision grid of a searched schedule (eval/search_static.py JSON), or of a FORA
    interval given as ``every_n:N`` (compute every branch at steps k % N == 0, timestep reuse else).
    ``reuse``: replace every reuse decision by that direction (same compute steps)."""
    spec = str(path)
    if spec.startswith("every_n:"):
        if steps is None or branches is None:
            raise ValueError("an every_n:N prior needs the number of steps and branches")
        grid = steps_grid(range(0, steps, int(spec.split(":", 1)[1])), steps, branches)
    else:
        grid = tts.plans.from_tensor(json.loads(Path(path).read_text())["grid"]).decisions[0]
    if reuse is not None:
        (reuse,) = tts.plans.check_directions((reuse,))
        grid = torch.where(grid == tts.plans.COMPUTE, grid, torch.full_like(grid, tts.plans.DIRECTIONS[reuse]))
    return grid


class RecordingPlan(PrunerPlan):
    """Test-time decisions (sequential), keeping the last call's codes for the sparsity statistics."""

    def __init__(self, pruner, mode: str = "argmax", sparsity: Optional[float] = None):
        super().__init__(pruner, mode=mode, sparsity=sparsity if mode == "budget" else None, parallel=False)

    def _decide(self, memory, blocking: bool = False) -> None:
        super()._decide(memory, blocking)
        self.last_codes = self._result


def mean_of(rows: list[dict], key: str) -> float:
    n = sum(r["frames"] for r in rows)
    return sum(r[key] * r["frames"] for r in rows) / max(n, 1)


def _as_json(args) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}


def fit(pruner, args, *, train_epoch: Callable, validate: Callable[[], list[dict]],
        metadata: Callable[[], dict], steps: int, memory_tokens: int,
        warm_start: Optional[Callable[[], dict]] = None) -> dict:
    """Train ``pruner`` for ``args.epochs``; returns the best epoch's row. ``metadata()`` adds the
    backbone's details to the checkpoint; ``warm_start()`` (before epoch 1 of a fresh run) may fit the
    pruner to something and return extra fields for an epoch-0 row that is validated like the others."""
    opt = torch.optim.AdamW(pruner.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda e: min(1.0, (e + 1) / max(1, args.epochs // 5)) * 0.5 * (1 + math.cos(math.pi * e / args.epochs)))
    state_path = (args.run_dir or Path("runs") / args.out.name) / "pruner_state.pt"
    epoch, history, best, best_state = 0, [], None, None
    if args.resume and state_path.exists():
        st = torch.load(state_path, map_location="cpu", weights_only=False)
        pruner.load_state_dict(st["pruner"])
        opt.load_state_dict(st["opt"])
        sched.load_state_dict(st["sched"])
        epoch, history, best, best_state = st["epoch"], st["history"], st["best"], st["best_state"]
        rng_states = st.get("rng")
        print(f"resumed after epoch {epoch}")
    else:
        rng_states = None
    if args.epochs < 1:
        raise SystemExit("--epochs must be >= 1")

    def score(row: dict) -> float:
        return row["val_l1"] + args.lam * abs(row["val_sparsity"] - args.sparsity)

    if epoch == 0 and (warm_start is not None or args.prior is not None):
        row = {"epoch": 0, **(warm_start() if warm_start is not None else {})}
        v = validate()
        row.update({f"val_{k}": mean_of(v, k) for k in ("l1", "sparsity")})
        row["val_score"] = score(row)
        print(" ".join(f"{k}={x:.4g}" for k, x in row.items()))
        history.append(row)
        best, best_state = row, {k: x.clone() for k, x in pruner.state_dict().items()}
    rng = np.random.default_rng(args.seed)
    noise_rng = torch.Generator().manual_seed(args.seed + 1000)
    if rng_states is not None:  # continue the same shuffles and noise as an uninterrupted run
        rng.bit_generator.state, _ = rng_states[0], noise_rng.set_state(rng_states[1])
    t_start, train_seconds = time.time(), (history[-1].get("train_seconds", 0.0) if history else 0.0)
    for epoch in range(epoch, args.epochs):
        pruner.train()
        stats = train_epoch(opt, rng, noise_rng, epoch)
        lr = opt.param_groups[0]["lr"]
        sched.step()
        v = validate()
        row = {"epoch": epoch + 1, **{f"train_{k}": mean_of(stats, k) for k in ("l1", "sparsity")},
               **{f"val_{k}": mean_of(v, k) for k in ("l1", "sparsity")}, "lr": lr}
        row["val_score"] = score(row)
        train_seconds += time.time() - t_start
        t_start = time.time()
        row["train_seconds"] = train_seconds
        history.append(row)
        print(" ".join(f"{k}={x:.4g}" for k, x in row.items()))
        if best is None or row["val_score"] < best["val_score"]:
            best, best_state = row, {k: x.clone() for k, x in pruner.state_dict().items()}
        with atomic_path(state_path) as tmp:
            torch.save({"pruner": pruner.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "epoch": epoch + 1, "history": history, "best": best, "best_state": best_state,
                        "rng": (rng.bit_generator.state, noise_rng.get_state())}, tmp)
        # the best epoch's weights, with the history so far: a usable checkpoint after every epoch
        meta = provenance(seeds={"train": args.seed})
        meta.update(_as_json(args), **metadata(), best_epoch=best, history=history, train_seconds=train_seconds,
                    pruner_macs_per_call=pruner.macs(steps, memory_tokens))
        current = {k: x.clone() for k, x in pruner.state_dict().items()}
        pruner.load_state_dict(best_state)
        save_pruner(pruner, args.out, metadata=meta)
        pruner.load_state_dict(current)
    print(f"best epoch {best['epoch']}: val L1 {best['val_l1']:.4f}, val sparsity {best['val_sparsity']:.3f}; "
          f"wrote {args.out}.safetensors/.json")
    return best
