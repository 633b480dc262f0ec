"""Training a pruner: the options (:class:`PrunerTrainingConfig`) and the loop (:func:`fit`).

:func:`fit` runs the epochs, validates each under the test-time rule (``val_mode``), keeps the best
epoch, writes the checkpoint after every epoch and keeps a resumable state. What one epoch of
training and one validation pass do depends on the backbone and is passed in as two functions
(:mod:`tts.policy_training` does it for a Diffusion Policy, from recorded trajectories):

- ``train_epoch(opt, rng, noise_rng, epoch, progress)`` -> rows ``{"l1", "sparsity", "frames"}``;
- ``validate()`` -> the same rows, with test-time decisions (see :class:`RecordingPlan`); any other
  key of its rows (e.g. the share of each reuse direction) is averaged into the epoch's row as ``val_<key>``.

``train_epoch`` also gets an :class:`EpochProgress` as a fifth argument: a trainer that calls
``progress.done(rows)`` after each batch group makes the epoch resumable mid-way (the state is saved
then, and a resumed run skips the first ``progress.skip`` groups, whose rows are ``progress.rows``,
with the shuffle, noise and dropout generators where the interrupted run had them).

A stop can be requested while a run trains: create the file ``<run_dir>/STOP`` (:attr:`PrunerTrainingConfig.stop_path`).
The run stops at its next save (after the batch group, or the epoch, in progress), removes the file
and raises :class:`TrainingStopped`; ``resume=True`` continues it with nothing lost.

The score of an epoch is val L1 + ``lam`` * |val sparsity - ``sparsity``|. The best epoch's weights
are written as ``<out>.safetensors/.json`` after every epoch (with the history so far and the
metadata passed in), and the full state (pruner, optimizer, schedule, random generators) under
``run_dir`` (default ``runs/<out name>/``), so that ``resume=True`` continues an interrupted run
exactly where it stopped.
"""
from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from .io import atomic_path, device_name
from .plans import COMPUTE, DIRECTIONS, check_directions, check_sparsity, from_tensor
from .pruner import PrunerModule, PrunerPlan, save_pruner
from .static_search import steps_grid

__all__ = ["EpochProgress", "GridSource", "PRECISIONS", "PrunerTrainingConfig", "RecordingPlan", "TrainingStopped", "fit",
           "mean_of", "read_grid", "training_finished"]

# a decision grid [K, nb]: a schedule JSON path (eval/search_static.py), "every_n:N", a tensor of codes,
# or one "CFTR" string per step
GridSource = Union[str, Path, torch.Tensor, Sequence[str]]

# options a resumed run must share with the run it continues (the rest may change, e.g. more epochs; the
# precision too, as a run may move to a machine without fast bfloat16, and each change is recorded)
_RESUME_MUST_MATCH = ("directions", "sparsity", "lam", "lr", "weight_decay", "batch", "forecast", "train_budget",
                      "n_train", "seed", "lr_schedule", "clip_grad", "loss_space", "paired")
PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16}


def lr_factor(epoch: int, epochs: int, schedule: str) -> float:
    """Learning-rate multiplier of ``epoch`` (0-based): linear warm-up over the first fifth of the
    epochs, then cosine or linear decay."""
    warm = min(1.0, (epoch + 1) / max(1, epochs // 5))
    if schedule == "linear":
        return warm * max(0.0, 1.0 - epoch / epochs)
    return warm * 0.5 * (1 + math.cos(math.pi * epoch / epochs))


@dataclass
class PrunerTrainingConfig:
    """Options of :func:`fit` (and of the backbone trainers built on it)."""

    out: Path  # the checkpoint, without suffix: <out>.safetensors + <out>.json
    directions: Union[str, Sequence[str]] = ("forward", "timestep", "rollout")  # or "forward,timestep"
    sparsity: float = 0.93  # target fraction of reused (step, branch) decisions
    lam: float = 1.0  # weight of the sparsity term
    epochs: int = 6
    batch: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    hidden: int = 64  # the pruner's width
    heads: int = 4  # attention heads of its decoder layer
    ffn: int = 128  # width of its feed-forward layer
    # learning rate per epoch: "cosine" (warm-up over the first fifth, then cosine decay) or "linear"
    # (the same warm-up, then linear decay to zero: the reference's schedule)
    lr_schedule: str = "cosine"
    clip_grad: Optional[float] = 1.0  # gradient-norm clip of the pruner's parameters; None: no clipping
    # the pruner's forward/backward in training: "float32", or "bfloat16" autocast (mixed precision:
    # float32 weights, optimizer and gates; about 2x faster on CPUs with bfloat16 instructions)
    precision: str = "float32"
    # train (and validate) with TaylorSeer-style forecasting timestep reuse of this order; use the same
    # forecast at test time
    forecast: int = 0
    # a searched static schedule whose decisions become fixed prior logits; the pruner (head
    # zero-initialised) learns per-sample corrections
    prior: Optional[GridSource] = None
    # map every reuse decision of the prior to this direction (single-direction variants of a
    # searched schedule, e.g. its compute steps with rollout reuse in between)
    prior_reuse: Optional[str] = None
    # training gates take the exact-budget decision (top 1 - sparsity by compute probability) in the
    # forward: sparsity fixed, the pruner learns the ranking
    train_budget: bool = False
    prior_margin: float = 3.0  # logit of the prior's option (smaller: the pruner moves away sooner)
    tie_branches: bool = False  # one decision per step for all branches (step-level pruner)
    step_query: bool = False  # with tie_branches: one decoder query per step instead of one per branch
    val_mode: str = "argmax"  # test-time rule of validation and checkpoint selection; budget: exactly sparsity
    n_train: int = 32  # training trajectories / samples
    n_val: int = 16  # validation trajectories / samples
    seed: int = 0
    run_dir: Optional[Path] = None  # resumable state; default runs/<out name>
    resume: bool = False  # continue from the state in run_dir, if there is one

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.run_dir is not None:
            self.run_dir = Path(self.run_dir)
        if isinstance(self.directions, str):
            self.directions = self.directions.split(",")
        self.directions = check_directions(self.directions)
        if not self.directions:
            raise ValueError("a pruner needs at least one reuse direction")
        self.sparsity = check_sparsity(self.sparsity)
        if self.prior_reuse is not None:
            check_directions((self.prior_reuse,))
        for name in ("epochs", "batch", "n_train"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.n_val < 0:
            raise ValueError(f"n_val must be >= 0, got {self.n_val}")
        if self.lr_schedule not in ("cosine", "linear"):
            raise ValueError(f"lr_schedule must be 'cosine' or 'linear', got {self.lr_schedule!r}")
        if self.clip_grad is not None and self.clip_grad <= 0:
            raise ValueError(f"clip_grad must be positive or None (no clipping), got {self.clip_grad}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {self.precision!r}")
        if self.val_mode not in ("argmax", "budget"):
            raise ValueError(f"val_mode must be 'argmax' or 'budget', got {self.val_mode!r}")
        if self.step_query and not self.tie_branches:
            raise ValueError("step_query (one query per step) needs tie_branches=True (step-level decisions)")

    @property
    def autocast(self) -> Optional[torch.dtype]:
        """The dtype of :attr:`precision` for :class:`tts.pruner.PrunerPlan` (None: float32)."""
        return PRECISIONS[self.precision]

    @property
    def state_path(self) -> Path:
        """Where the resumable training state is saved: ``<run_dir>/pruner_state.pt``."""
        return (self.run_dir or Path("runs") / self.out.name) / "pruner_state.pt"

    @property
    def stop_path(self) -> Path:
        """The file that requests a stop at the next save: ``<run_dir>/STOP`` (see :class:`TrainingStopped`)."""
        return self.state_path.parent / "STOP"

    def to_json(self) -> dict[str, Any]:
        """The options as JSON values (paths as strings, a grid as one "CFTR" string per step)."""
        return {f.name: _jsonable(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, options: Mapping[str, Any]) -> "PrunerTrainingConfig":
        """A config from the options in ``options`` (other keys are ignored: e.g. a checkpoint's
        metadata, or ``vars()`` of parsed command-line arguments)."""
        return cls(**{f.name: options[f.name] for f in fields(cls) if f.name in options})


def _jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, torch.Tensor):
        return ["".join("CFTR"[int(c)] for c in row) for row in value.tolist()]
    if isinstance(value, tuple):
        return list(value)
    return value


def read_grid(source: GridSource, steps: Optional[int] = None, branches: Optional[int] = None,
              reuse: Optional[str] = None) -> torch.Tensor:
    """The [K, nb] decision grid of a searched schedule (an eval/search_static.py JSON path), of a
    FORA interval given as ``every_n:N`` (compute every branch at steps k % N == 0, timestep reuse
    else; needs ``steps`` and ``branches``), of a tensor of codes or of one "CFTR" string per step.
    ``reuse``: replace every reuse decision by that direction (same compute steps)."""
    if isinstance(source, torch.Tensor):
        if source.dim() != 2:
            raise ValueError(f"a decision grid is [steps, branches], got {tuple(source.shape)}")
        grid = from_tensor(source).decisions[0]
    elif isinstance(source, (list, tuple)):
        grid = from_tensor(list(source)).decisions[0]
    elif str(source).startswith("every_n:"):
        if steps is None or branches is None:
            raise ValueError("an every_n:N prior needs the number of steps and branches")
        grid = steps_grid(range(0, steps, int(str(source).split(":", 1)[1])), steps, branches)
    else:
        grid = from_tensor(json.loads(Path(source).read_text())["grid"]).decisions[0]
    if reuse is not None:
        (reuse,) = check_directions((reuse,))
        grid = torch.where(grid == COMPUTE, grid, torch.full_like(grid, DIRECTIONS[reuse]))
    return grid


class RecordingPlan(PrunerPlan):
    """Test-time decisions (sequential), keeping the last call's codes [B, K, nb] in ``last_codes``
    for the sparsity statistics of a validation pass."""

    def __init__(self, pruner: PrunerModule, mode: str = "argmax", sparsity: Optional[float] = None):
        super().__init__(pruner, mode=mode, sparsity=sparsity if mode == "budget" else None, parallel=False)

    def _decide(self, memory, blocking: bool = False) -> None:
        super()._decide(memory, blocking)
        self.last_codes = self._result


def mean_of(rows: list[dict], key: str) -> float:
    """Mean of ``key`` over rows, weighted by their ``frames``."""
    n = sum(r["frames"] for r in rows)
    return sum(r[key] * r["frames"] for r in rows) / max(n, 1)


def _val_means(rows: list[dict]) -> dict[str, float]:
    """``val_<key>``: the frame-weighted mean of every key of the validation rows (``l1``,
    ``sparsity`` and whatever else the trainer reports, e.g. the share of each reuse direction)."""
    keys = [k for k in (rows[0] if rows else {"l1": 0, "sparsity": 0}) if k != "frames"]
    return {f"val_{k}": mean_of(rows, k) for k in keys}


def _check_resume(state: dict, pruner: PrunerModule, config: PrunerTrainingConfig) -> None:
    path = config.state_path
    saved = state.get("pruner_config")
    if saved is not None and saved != asdict(pruner.config):
        diff = sorted(k for k in set(saved) | set(asdict(pruner.config))
                      if saved.get(k) != asdict(pruner.config).get(k))
        raise ValueError(f"{path} holds the training state of a different pruner ({', '.join(diff)} differ): "
                         "resume with the options of the interrupted run, or use another run_dir")
    options = state.get("config")
    if options is not None:
        now = config.to_json()
        diff = [k for k in _RESUME_MUST_MATCH if k in options and options[k] != now[k]]
        if diff:
            raise ValueError(f"{path} was trained with other {', '.join(diff)} "
                             f"({', '.join(f'{k}={options[k]!r}' for k in diff)}): resume with the options of "
                             "the interrupted run, or use another run_dir")
    try:
        pruner.load_state_dict(state["pruner"])
    except RuntimeError as e:  # a state written before the pruner's config was recorded in it
        raise ValueError(f"{path} holds the training state of a different pruner: {e}") from None


def _precision_log(state: Optional[dict], epoch: int, config: PrunerTrainingConfig, device: str,
                   say: Callable[[str], None]) -> list[dict]:
    """The precision and device of each stretch of a run: ``[{"epoch", "groups", "precision", "device"}]``,
    a stretch beginning after ``epoch`` finished epochs and ``groups`` groups of the next; a resume with
    another precision or on another device (e.g. a GPU's stretch continued on a CPU) starts a new
    stretch. A stretch saved without a device (older states) is not split by the device alone."""
    if state is None:
        return [{"epoch": 0, "groups": 0, "precision": config.precision, "device": device}]
    log = list(state.get("precision_log") or
               [{"epoch": 0, "groups": 0, "precision": state.get("config", {}).get("precision", "float32")}])
    last = log[-1]
    if last["precision"] != config.precision or last.get("device", device) != device:
        groups = (state.get("partial") or {}).get("groups", 0)
        say(f"{last['precision']} on {last.get('device', '?')} -> {config.precision} on {device} "
            f"from epoch {epoch + 1}, group {groups + 1}")
        log.append({"epoch": epoch, "groups": groups, "precision": config.precision, "device": device})
    return log


class TrainingStopped(Exception):
    """Raised by :func:`fit` when a stop was requested (:attr:`PrunerTrainingConfig.stop_path` exists),
    right after the resumable state was saved: ``resume=True`` continues the run where it stopped."""


class EpochProgress:
    """Where an epoch stands: ``skip`` groups already trained (their rows in ``rows``, from an
    interrupted run); ``done(rows)`` after each group saves a resumable state."""

    def __init__(self, skip: int = 0, rows: Optional[list] = None, save: Optional[Callable[[list], None]] = None):
        self.skip, self.rows, self._save = skip, list(rows or []), save

    def done(self, rows: list) -> None:
        """Record that the groups in ``rows`` are trained (saves the resumable state)."""
        if self._save is not None:
            self._save(rows)


def training_finished(checkpoint_json: Union[str, Path]) -> bool:
    """Whether the pruner checkpoint whose ``.json`` is ``checkpoint_json`` holds a finished training:
    :func:`fit` writes the best epoch so far after every epoch, so an interrupted run leaves a
    checkpoint whose history stops short of its ``epochs``. False when the file does not exist."""
    path = Path(checkpoint_json)
    if not path.exists():
        return False
    meta = json.loads(path.read_text())["metadata"]
    return bool(meta.get("history")) and meta["history"][-1]["epoch"] >= meta["epochs"]


def fit(pruner: PrunerModule, config: PrunerTrainingConfig, *, train_epoch: Callable, validate: Callable[[], list],
        steps: int, memory_tokens: int, metadata: Optional[Mapping[str, Any]] = None,
        warm_start: Optional[Callable[[], dict]] = None, log: Optional[Callable[[str], None]] = print) -> dict:
    """Train ``pruner`` for ``config.epochs``; returns the best epoch's row and leaves the best
    epoch's weights in ``pruner`` (and the checkpoint's metadata in ``pruner.metadata``).

    ``steps`` and ``memory_tokens``: the sampler's K and the condition memory's length (the pruner's
    MACs per call are recorded). ``metadata``: written into the checkpoint's metadata, first (e.g.
    provenance, the data's origin); the config's options follow unless ``metadata`` has them already.
    ``warm_start()`` (before epoch 1 of a fresh run) may fit the pruner to something and return extra
    fields for an epoch-0 row that is validated like the others (a run with a prior has that row too).
    """
    say = log or (lambda msg: None)
    opt = torch.optim.AdamW(pruner.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: lr_factor(e, config.epochs, config.lr_schedule))
    state_path = config.state_path
    epoch, history, best, best_state, st = 0, [], None, None, None
    if config.resume and state_path.exists():
        st = torch.load(state_path, map_location="cpu", weights_only=False)
        _check_resume(st, pruner, config)
        opt.load_state_dict(st["opt"])
        sched.load_state_dict(st["sched"])
        epoch, history, best, best_state = st["epoch"], st["history"], st["best"], st["best_state"]
        say(f"resumed after epoch {epoch}")
    precision_log = _precision_log(st, epoch, config, device_name(next(pruner.parameters()).device), say)
    if config.stop_path.exists():  # left by a run that ended before its next save
        config.stop_path.unlink()
        say(f"removed a stale stop request ({config.stop_path})")

    def score(row: dict) -> float:
        return row["val_l1"] + config.lam * abs(row["val_sparsity"] - config.sparsity)

    def snapshot() -> dict:
        return {k: x.clone() for k, x in pruner.state_dict().items()}

    if epoch == 0 and not history and (warm_start is not None or config.prior is not None):
        row = {"epoch": 0, **(warm_start() if warm_start is not None else {})}
        row.update(_val_means(validate()))
        row["val_score"] = score(row)
        say(" ".join(f"{k}={x:.4g}" for k, x in row.items()))
        history.append(row)
        best, best_state = row, snapshot()
    rng = np.random.default_rng(config.seed)
    noise_rng = torch.Generator().manual_seed(config.seed + 1000)
    partial = st.get("partial") if st is not None else None
    if st is not None:  # continue the same shuffles, noise and dropout as an uninterrupted run
        rng.bit_generator.state = st["rng"][0]
        noise_rng.set_state(st["rng"][1])
        if "torch_rng" in st:
            torch.set_rng_state(st["torch_rng"])
    if partial is not None:
        say(f"resumed epoch {epoch + 1} after {partial['groups']} groups")
    base = dict(metadata or {})
    for k, v in config.to_json().items():
        base.setdefault(k, v)
    meta = None
    # seconds spent training so far; a state saved mid-epoch also counts that epoch's trained groups
    # (a state saved before it recorded them: the last finished epoch's count)
    train_seconds = history[-1].get("train_seconds", 0.0) if history else 0.0
    train_seconds = st.get("train_seconds", train_seconds) if st is not None else train_seconds
    t_start = time.time()

    def save_state(done_epochs: int, mid: Optional[dict]) -> None:
        with atomic_path(state_path) as tmp:
            torch.save({"pruner": pruner.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "epoch": done_epochs, "history": history, "best": best, "best_state": best_state,
                        "rng": (rng.bit_generator.state, noise_rng.get_state()), "torch_rng": torch.get_rng_state(),
                        "pruner_config": asdict(pruner.config), "config": config.to_json(), "partial": mid,
                        "precision_log": precision_log, "train_seconds": train_seconds + time.time() - t_start}, tmp)

    def stop_if_requested(where: str) -> None:
        if config.stop_path.exists():
            config.stop_path.unlink()
            raise TrainingStopped(f"stopped {where}, as {config.stop_path} asked; the state is saved in "
                                  f"{state_path}: resume to continue")

    for epoch in range(epoch, config.epochs):
        pruner.train()
        if partial is not None:  # the interrupted epoch: its shuffle again (the generators of noise and
            # dropout were restored where its last saved group left them)
            start_rng, progress_rows, skip = partial["rng_at_start"], partial["rows"], partial["groups"]
            partial = None
        else:
            start_rng, progress_rows, skip = copy.deepcopy(rng.bit_generator.state), [], 0

        def save_partial(rows: list, done_epochs: int = epoch, start=start_rng) -> None:
            mid = {"groups": len(rows), "rows": list(rows), "rng_at_start": start}
            shuffled = rng.bit_generator.state  # saved as the epoch's start: the resumed run reshuffles
            rng.bit_generator.state = start
            save_state(done_epochs, mid)
            rng.bit_generator.state = shuffled
            stop_if_requested(f"in epoch {done_epochs + 1} of {config.epochs} after {len(rows)} groups")

        stats = train_epoch(opt, rng, noise_rng, epoch, EpochProgress(skip, progress_rows, save_partial))
        lr = opt.param_groups[0]["lr"]
        sched.step()
        v = validate()
        row = {"epoch": epoch + 1, **{f"train_{k}": mean_of(stats, k) for k in ("l1", "sparsity")},
               **_val_means(v), "lr": lr}
        row["val_score"] = score(row)
        train_seconds += time.time() - t_start
        t_start = time.time()
        row["train_seconds"] = train_seconds
        history.append(row)
        say(" ".join(f"{k}={x:.4g}" for k, x in row.items()))
        if best is None or row["val_score"] < best["val_score"]:
            best, best_state = row, snapshot()
        save_state(epoch + 1, None)
        # the best epoch's weights, with the history so far: a usable checkpoint after every epoch
        meta = dict(base, best_epoch=best, history=history, train_seconds=train_seconds,
                    precision_log=precision_log,
                    pruner_macs_per_call=pruner.macs(steps, memory_tokens))
        current = snapshot()
        pruner.load_state_dict(best_state)
        save_pruner(pruner, config.out, metadata=meta)
        pruner.load_state_dict(current)
        if epoch + 1 < config.epochs:
            stop_if_requested(f"after epoch {epoch + 1} of {config.epochs}")
    pruner.load_state_dict(best_state)
    if meta is not None:
        pruner.metadata = meta
    say(f"best epoch {best['epoch']}: val L1 {best['val_l1']:.4f}, val sparsity {best['val_sparsity']:.3f}; "
        f"wrote {config.out}.safetensors/.json")
    return best
