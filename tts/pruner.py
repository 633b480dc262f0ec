"""The learned pruner and the plan that runs it before each sampling call.

The pruner reads the denoiser's own condition memory for all K steps, [B, K, Tc, D] (for DP-T the
condition encoder's output, computed in one batched call: the pruner shares it, nothing is encoded
twice), and predicts logits [B, K, nb, O] over {compute} + the enabled directions for every branch
at every step. Architecture: Linear(D -> h) on the memory; fixed sinusoidal (or learned) branch
queries; one pre-norm decoder layer (query self-attention, cross-attention to the memory, ReLU FFN);
Linear(h -> O). The query self-attention does not depend on the input, so in eval mode it is
computed once and cached. No flip of the K axis: the gates of step k come from memory k.

:class:`PrunerPlan` feeds the engine. ``mode``: ``"argmax"`` (the paper), ``"budget"`` (exact
sparsity per sample, see :mod:`tts.gates`) or ``"ste"`` (training: differentiable gates, every
branch computed and mixed). ``parallel``: the pruner runs on a side CUDA stream (GPU) or a worker
thread (CPU) while step 0, which is always dense, runs; step 1 waits for it. ``"auto"`` (default)
uses the thread on CPU only when torch leaves cores idle (``torch.get_num_threads() <
usable cores): when torch's threads already use every core, a second thread slows step 0 by
more than the overlap saves.
"""
from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import torch
import torch.nn as nn

from .gates import argmax_codes, budget_codes, budget_ste_gates, ste_gates
from .io import atomic_path, checkpoint_pair
from .plans import COMPUTE, DIRECTIONS, TIMESTEP, Plan, check_directions, check_sparsity

__all__ = ["PrunerConfig", "Pruner", "StaticRouter", "build_pruner", "PrunerPlan", "pruner_loss", "save_pruner",
           "load_pruner", "distill_schedule"]


@dataclass
class PrunerConfig:
    """Shape and options of a pruner: the policy's branches and steps, the reuse directions, the width."""

    memory_dim: int  # D of the condition memory
    num_branches: int  # nb: prunable branches per denoising step
    directions: tuple[str, ...] = ("forward", "timestep", "rollout")
    hidden: int = 64
    heads: int = 4
    ffn: int = 128
    dropout: float = 0.1
    queries: str = "sinusoidal"  # or "learned"
    branch_names: list[str] = field(default_factory=list)  # of the model it was trained on
    kind: str = "transformer"  # or "static": one learned decision per (step, branch), see StaticRouter
    steps: int = 0  # K, for kind="static" and for a prior
    prior: bool = False  # add fixed prior logits [steps, nb, O] (a searched schedule) to the pruner's own
    head_bias: Optional[list[float]] = None  # initial head bias per option (default: compute 2, reuse 0)
    tie_branches: bool = False  # one decision per (sample, step) for all branches: whole steps computed or reused
    step_query: bool = False  # with tie_branches: one decoder query per step instead of one per branch

    def __post_init__(self) -> None:
        self.directions = check_directions(self.directions)
        if not self.directions:
            raise ValueError("a pruner needs at least one reuse direction")
        if self.queries not in ("sinusoidal", "learned"):
            raise ValueError(f"queries must be 'sinusoidal' or 'learned', got {self.queries!r}")
        if self.head_bias is not None and len(self.head_bias) != len(self.codes):
            raise ValueError(f"head_bias needs one value per option {self.codes}, got {self.head_bias}")
        if self.kind not in ("transformer", "static"):
            raise ValueError(f"kind must be 'transformer' or 'static', got {self.kind!r}")
        if self.kind == "static" and self.tie_branches:
            raise ValueError("tie_branches applies to the transformer pruner, not the static router")
        if self.step_query and not self.tie_branches:
            raise ValueError("step_query (one query per step) needs tie_branches=True (step-level decisions)")
        if (self.kind == "static" or self.prior) and self.steps < 1:
            raise ValueError("a static router or a prior needs steps= (the number of denoising steps K)")

    @property
    def codes(self) -> list[int]:
        """Decision code of each head option: compute, then the directions in canonical order."""
        return [COMPUTE] + [DIRECTIONS[d] for d in self.directions]


def _sinusoidal(n: int, dim: int) -> torch.Tensor:
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    freq = torch.exp(-math.log(10000.0) * torch.arange(0, dim, 2, dtype=torch.float32) / dim)
    out = torch.zeros(n, dim)
    out[:, 0::2] = torch.sin(pos * freq)
    out[:, 1::2] = torch.cos(pos * freq[: dim // 2])
    return out


def dropout_fast(x: torch.Tensor, p: float, training: bool) -> torch.Tensor:
    """Dropout whose mask comes from 15 random bits per element, drawn four to an int64 from torch's
    global generator: several times faster than ``torch.nn.functional.dropout`` on the CPU, where
    drawing the mask dominates the pruner's training step. Drop probability round(p * 2^15) / 2^15."""
    if not training or p == 0.0:
        return x
    n = x.numel()
    # random_() on int64 is uniform on [0, 2^63): each 16-bit quarter has 15 uniform low bits
    bits = torch.empty((n + 3) // 4, dtype=torch.int64, device=x.device).random_().view(torch.int16)[:n]
    keep = (bits & 0x7FFF) >= round(p * 32768)
    return x * keep.view(x.shape).to(x.dtype).mul_(1.0 / (1.0 - p))


class _Dropout(nn.Module):
    def __init__(self, p: float):
        super().__init__()
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return dropout_fast(x, self.p, self.training)


class _QueryDecoderLayer(nn.Module):
    """Pre-norm decoder layer, split so the input-independent query self-attention can be cached."""

    def __init__(self, h: int, heads: int, ffn: int, dropout: float):
        super().__init__()
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(h), nn.LayerNorm(h), nn.LayerNorm(h)
        self.self_attn = nn.MultiheadAttention(h, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(h, heads, dropout=dropout, batch_first=True)
        self.ff = nn.Sequential(nn.Linear(h, ffn), nn.ReLU(), _Dropout(dropout), nn.Linear(ffn, h))
        self.drop = _Dropout(dropout)

    def queries(self, q: torch.Tensor) -> torch.Tensor:
        x = self.norm1(q)
        return q + self.drop(self.self_attn(x, x, x, need_weights=False)[0])

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        """``x`` [nq, h]: the query state, the same for every sample; ``memory`` [N, Tc, h]. -> [N, nq, h]."""
        x = x + self.drop(self._cross(x, memory))
        return x + self.drop(self.ff(self.norm3(x)))

    def _cross(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        """``self.cross_attn(norm2(x), memory, memory)`` for a query shared by all N samples, computed
        without per-sample work on the queries: their projection is done once, and the output
        projection is applied to the Tc values per head (Wo sum_t a_t v_t = sum_t a_t (Wo v_t)), not
        to the nq attention outputs. Equal to the module's own forward up to float summation order."""
        attn = self.cross_attn
        (nq, h), (n, tc, _) = x.shape, memory.shape
        heads = attn.num_heads
        w_q, w_k, w_v = attn.in_proj_weight.chunk(3)
        b_q, b_k, b_v = attn.in_proj_bias.chunk(3)
        q = nn.functional.linear(self.norm2(x), w_q, b_q).view(nq, heads, -1)  # [nq, H, d]
        k = nn.functional.linear(memory, w_k, b_k).view(n, tc, heads, -1)  # [N, Tc, H, d]
        v = nn.functional.linear(memory, w_v, b_v).view(n, tc, heads, -1)
        scores = torch.einsum("qhd,nthd->nqht", q, k) * q.shape[-1] ** -0.5
        a = dropout_fast(scores.softmax(-1), attn.dropout, self.training)  # [N, nq, H, Tc]
        w_o = attn.out_proj.weight.view(h, heads, -1)  # [h_out, H, d]
        u = torch.einsum("nthd,ohd->nhto", v, w_o)  # every value through its head's slice of Wo
        out = torch.bmm(a.reshape(n, nq, heads * tc), u.reshape(n, heads * tc, h))
        return out + attn.out_proj.bias


class Pruner(nn.Module):
    """The learned pruner: one query per branch cross-attends to the condition memory of each step and
    a head gives logits over compute and the reuse directions (the paper's transformer decoder)."""

    def __init__(self, config: PrunerConfig):
        super().__init__()
        self.config = config
        c = config
        self.memory_proj = nn.Linear(c.memory_dim, c.hidden)
        n_queries = 1 if c.step_query else c.num_branches
        if c.queries == "learned":
            self.block_queries = nn.Parameter(_sinusoidal(n_queries, c.hidden))
        else:
            self.register_buffer("block_queries", _sinusoidal(n_queries, c.hidden), persistent=False)
        self.layer = _QueryDecoderLayer(c.hidden, c.heads, c.ffn, c.dropout)
        self.head = nn.Linear(c.hidden, len(c.codes))
        for lin in (self.memory_proj, self.head):
            nn.init.xavier_uniform_(lin.weight)
            nn.init.zeros_(lin.bias)
        if c.prior:  # decisions start as the prior schedule; the pruner learns per-observation corrections
            self.register_buffer("prior", torch.zeros(c.steps, c.num_branches, len(c.codes)))
            nn.init.zeros_(self.head.weight)
        else:
            self.prior = None
            with torch.no_grad():  # start near "compute everything" so early training is stable
                if c.head_bias is None:
                    self.head.bias[0] = 2.0
                else:
                    self.head.bias.copy_(torch.tensor(c.head_bias))
        self._query_cache: Optional[torch.Tensor] = None

    def train(self, mode: bool = True) -> "Pruner":
        self._query_cache = None
        return super().train(mode)

    def _query_state(self) -> torch.Tensor:
        if self.training or torch.is_grad_enabled():
            return self.layer.queries(self.block_queries[None])[0]
        if self._query_cache is None:
            self._query_cache = self.layer.queries(self.block_queries[None])[0]
        return self._query_cache

    def forward(self, memory: torch.Tensor) -> torch.Tensor:
        """memory [B, K, Tc, D] -> logits [B, K, nb, O]."""
        if memory.dim() != 4 or memory.shape[-1] != self.config.memory_dim:
            raise ValueError(
                f"pruner expects memory [B, K, Tc, {self.config.memory_dim}], got {tuple(memory.shape)}"
            )
        B, K, Tc, D = memory.shape
        mem = self.memory_proj(memory.reshape(B * K, Tc, D))
        q = self._query_state()  # [nb or 1 (step_query), h]
        x = self.layer(q, mem)
        nb = self.config.num_branches
        logits = self.head(x).reshape(B, K, q.shape[0], -1)
        if self.config.tie_branches:  # step-level decisions: the branches' logits averaged (or the step query's)
            logits = logits.mean(2, keepdim=True).expand(B, K, nb, logits.shape[-1])
        if self.prior is not None:
            if K != self.prior.shape[0]:
                raise ValueError(f"the pruner's prior schedule has {self.prior.shape[0]} steps, the sampler runs {K}")
            logits = logits + self.prior
        return logits

    def set_prior(self, grid: torch.Tensor, margin: float = 3.0) -> None:
        """Prior logits from a decision grid [K, nb] (e.g. a searched schedule): the grid's option gets
        ``margin``; where the grid computes, the timestep option (else the first reuse option) gets
        ``margin / 2``, so that a forced reuse (budget mode) falls back to it."""
        if self.prior is None:
            raise ValueError("this pruner was built without a prior (PrunerConfig(prior=True, steps=K))")
        codes = self.config.codes
        if tuple(grid.shape) != tuple(self.prior.shape[:2]):
            raise ValueError(f"schedule shape {tuple(grid.shape)} != [steps, branches] {tuple(self.prior.shape[:2])}")
        unknown = sorted(set(grid.unique().tolist()) - set(codes))
        if unknown:
            raise ValueError(f"the schedule uses decision codes {unknown} the pruner has no option for ({codes})")
        option = torch.tensor([codes.index(c) for c in grid.flatten().tolist()]).reshape(grid.shape)
        fallback = codes.index(TIMESTEP) if TIMESTEP in codes else 1
        prior = torch.zeros_like(self.prior)
        prior[..., fallback] = torch.where(option == 0, margin / 2, 0.0)
        prior.scatter_(-1, option[..., None], margin)
        self.prior.copy_(prior)

    def macs(self, steps: int, memory_tokens: int) -> float:
        """MACs of one call for one sample (K steps), counted by PyTorch's FlopCounterMode."""
        from .flops import flop_counter_macs

        was = self.training
        self.eval()
        try:
            mem = torch.zeros(1, steps, memory_tokens, self.config.memory_dim, device=self.head.weight.device)
            with torch.no_grad():
                self._query_cache = None
                total = flop_counter_macs(lambda: self(mem))
        finally:
            self.train(was)
        return total


class StaticRouter(nn.Module):
    """Learning-to-Cache-style baseline: one learned logit vector per (step, branch), the same for
    every observation. Trained by the same loop as :class:`Pruner`; ignores the memory's content."""

    def __init__(self, config: PrunerConfig):
        super().__init__()
        if config.kind != "static":
            raise ValueError("StaticRouter needs PrunerConfig(kind='static', steps=K)")
        self.config = config
        logits = torch.zeros(config.steps, config.num_branches, len(config.codes))
        logits[..., 0] = 2.0  # start near "compute everything", like the pruner
        self.logits = nn.Parameter(logits)

    def forward(self, memory: torch.Tensor) -> torch.Tensor:
        """memory [B, K, ...] -> logits [B, K, nb, O] (the same for every sample)."""
        B, K = memory.shape[:2]
        if K != self.config.steps:
            raise ValueError(f"static router was trained for {self.config.steps} steps, the sampler runs {K}")
        return self.logits[None].expand(B, -1, -1, -1)

    def macs(self, steps: int, memory_tokens: int) -> float:
        """0: a table lookup."""
        return 0.0


def build_pruner(config: PrunerConfig) -> nn.Module:
    """A :class:`Pruner` or, for ``kind="static"``, a :class:`StaticRouter`."""
    return StaticRouter(config) if config.kind == "static" else Pruner(config)


PrunerModule = Union[Pruner, StaticRouter]


def _usable_cores() -> int:
    """CPUs this process may run on (affinity / container limits), not all of the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class PrunerPlan(Plan):
    """Decisions from a :class:`Pruner`, computed once per sampling call from the condition memory."""

    def __init__(self, pruner: PrunerModule, mode: str = "argmax", sparsity: Optional[float] = None,
                 parallel: Union[bool, str] = "auto", autocast: Optional[torch.dtype] = None):
        """``autocast``: with ``mode="ste"``, run the pruner's forward (and so its backward) under
        ``torch.autocast`` to this dtype (e.g. ``torch.bfloat16``: mixed-precision training); the gates
        stay float32."""
        if mode not in ("argmax", "budget", "ste"):
            raise ValueError(f"mode must be 'argmax', 'budget' or 'ste', got {mode!r}")
        if mode == "budget" and sparsity is None:
            raise ValueError("mode='budget' needs sparsity=")
        if sparsity is not None:  # budget, or ste with the exact-budget forward (training)
            sparsity = check_sparsity(sparsity)
        self.pruner = pruner if mode == "ste" else pruner.eval()  # no dropout at test time
        self.mode = mode
        self.sparsity = sparsity
        if parallel not in (True, False, "auto"):
            raise ValueError(f"parallel must be True, False or 'auto', got {parallel!r}")
        self.parallel = parallel if mode != "ste" else False
        if autocast is not None and mode != "ste":
            raise ValueError("autocast applies to training (mode='ste'); decisions at test time run in float32")
        self.autocast = autocast
        self.codes = pruner.config.codes
        self._whole_steps = bool(getattr(pruner.config, "tie_branches", False))  # budget counts whole steps
        self.uses = frozenset(self.codes)
        self.soft = mode == "ste"
        self.num_steps = pruner.config.steps or None
        self._pending: Optional[threading.Thread] = None
        self._gpu: Optional[tuple] = None  # (pinned host decisions, start event, done event)
        self._observed = False  # observe() ran for the call about to start
        self._tables: dict[torch.device, torch.Tensor] = {}
        self._result: Optional[torch.Tensor] = None
        self._error: Optional[BaseException] = None
        self.gates: Optional[torch.Tensor] = None
        self.timing: dict[str, float] = {}
        self._macs_key: Optional[tuple] = None
        self.macs_per_sample = 0.0

    def bind(self, num_branches: int, branch_kinds: Sequence[str]) -> None:
        super().bind(num_branches, branch_kinds)
        c = self.pruner.config
        if c.num_branches != num_branches:
            raise ValueError(
                f"pruner was trained for a model with {c.num_branches} branches per step, this model "
                f"has {num_branches}: it does not belong to this model"
            )

    def describe(self) -> str:
        extra = f":{self.sparsity}" if self.sparsity is not None else ""
        return f"pruner[{self.mode}{extra}]({','.join(self.pruner.config.directions)})"

    # ---------------------------------------------------------------- engine interface
    def observe(self, memory: torch.Tensor, dense: bool) -> None:
        """Condition memory [B, K, Tc, D] of the call about to start. ``dense``: the engine will
        compute everything anyway (first call of an episode), so no decisions are needed."""
        if self._pending is not None:  # a previous call ended early (an exception): never reuse its thread
            self._pending.join()
            self._pending = None
        self.timing = {"pruner": 0.0, "wait": 0.0}
        self._result, self._error, self.gates, self._gpu = None, None, None, None
        self._observed = True
        trained = self.pruner.config.steps
        if trained and memory.shape[1] != trained:
            raise ValueError(f"pruner was trained for {trained} steps, the sampler runs {memory.shape[1]}: train one "
                             "for this sampler (eval/train_pruner.py on trajectories of the same base)")
        key = tuple(memory.shape[1:])
        if key != self._macs_key:
            self._macs_key = key
            self.macs_per_sample = self.pruner.macs(memory.shape[1], memory.shape[2])
        if dense:
            return
        if self.mode == "ste":
            with torch.autocast(memory.device.type, dtype=self.autocast, enabled=self.autocast is not None):
                logits = self.pruner(memory).float()
            self.gates, self.probs = (ste_gates(logits) if self.sparsity is None
                                      else budget_ste_gates(logits, self.sparsity, self._whole_steps))
            return
        memory = memory.detach()
        if not self.parallel:
            self._decide(memory, blocking=True)
        elif memory.is_cuda:
            self._launch_on_side_stream(memory)
        elif self.parallel == "auto" and torch.get_num_threads() >= _usable_cores():
            self._decide(memory, blocking=True)  # no idle core to overlap on
        else:  # CPU: a worker thread (torch ops release the GIL) while step 0 runs
            self._pending = threading.Thread(target=self._decide, args=(memory,), daemon=True)
            self._pending.start()

    def begin_call(self, call_index: int, batch: int) -> None:
        """A sampling call that did not go through the condition encoder has no decisions: never
        serve it the previous call's."""
        if not self._observed:
            self._result, self.gates, self._gpu = None, None, None
        self._observed = False

    def _table(self, device: torch.device) -> torch.Tensor:
        """Option -> decision code, on ``device`` (built once: a host->device copy syncs a stream)."""
        table = self._tables.get(device)
        if table is None:
            table = self._tables[device] = torch.tensor(self.codes, dtype=torch.int8, device=device)
        return table

    def _codes(self, memory: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        logits = self.pruner(memory)
        if self.mode == "budget":
            return budget_codes(logits, table, self.sparsity, self._whole_steps)
        return argmax_codes(logits, table)

    def _decide(self, memory: torch.Tensor, blocking: bool = False) -> None:
        """Decisions on the CPU; ``blocking``: in the sampling thread, so all of it is waiting."""
        t0 = time.perf_counter()
        try:
            with torch.no_grad():
                self._result = self._codes(memory, self._table(memory.device)).cpu()
        except BaseException as e:  # re-raised in the sampling thread
            self._error = e
        self.timing["pruner"] = time.perf_counter() - t0
        if blocking:
            self.timing["wait"] = self.timing["pruner"]

    def _launch_on_side_stream(self, memory: torch.Tensor) -> None:
        """GPU: the pruner runs on a side stream that waits for the encoder's output; its decisions
        are copied to pinned host memory without blocking, and an event marks the copy. Nothing
        waits for it until step 1 (step 0 is dense), so the decoder's step 0 overlaps it."""
        table = self._table(memory.device)  # outside the side stream (built once per device)
        main = torch.cuda.current_stream(memory.device)
        side = torch.cuda.Stream(memory.device)
        side.wait_stream(main)
        start, done = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        with torch.cuda.stream(side), torch.no_grad():
            start.record(side)
            codes = self._codes(memory, table)
            host = torch.empty(codes.shape, dtype=codes.dtype, pin_memory=True)
            host.copy_(codes, non_blocking=True)
            done.record(side)
        memory.record_stream(side)  # the allocator must not recycle it before the side stream is done
        self._gpu = (host, start, done)

    def _wait(self) -> torch.Tensor:
        if self._pending is not None:
            t0 = time.perf_counter()
            self._pending.join()
            self._pending = None
            self.timing["wait"] = time.perf_counter() - t0
        if self._gpu is not None:
            host, start, done = self._gpu
            t0 = time.perf_counter()
            done.synchronize()
            self.timing["wait"] = time.perf_counter() - t0
            self.timing["pruner"] = start.elapsed_time(done) / 1e3
            self._result, self._gpu = host, None
        if self._error is not None:
            raise self._error
        if self._result is None:
            raise RuntimeError(
                "the pruner has no condition memory for this call: the model adapter must declare "
                "Target.condition (the function that encodes the condition for all steps)"
            )
        return self._result

    def step(self, k: int, batch: int) -> torch.Tensor:
        codes = self._wait()
        if codes.shape[0] != batch:
            raise ValueError(f"pruner decided for {codes.shape[0]} samples, the batch has {batch}")
        if k >= codes.shape[1]:
            raise ValueError(f"pruner predicted {codes.shape[1]} steps, the sampler ran step {k}")
        return codes[:, k]

    def soft_step(self, k: int) -> torch.Tensor:
        """Training: straight-through gates [B, nb, O] for step k."""
        if self.gates is None:
            raise RuntimeError("mode='ste' gates missing: the condition memory was not observed")
        return self.gates[:, k]


# -------------------------------------------------------------------- checkpoints
def save_pruner(pruner: PrunerModule, path: Path, metadata: Optional[dict] = None) -> None:
    """``<path>.safetensors`` (weights) + ``<path>.json`` (config and provenance), atomically."""
    from safetensors.torch import save_file

    weights, meta = checkpoint_pair(path)
    state = {k: v.detach().contiguous().cpu() for k, v in pruner.state_dict().items()}
    with atomic_path(weights) as tmp:
        save_file(state, str(tmp))
    doc = {"format": "tts-pruner-v1", "config": asdict(pruner.config), "metadata": metadata or {}}
    with atomic_path(meta) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2))


def load_pruner(path: Path) -> PrunerModule:
    """A pruner saved by :func:`save_pruner` (``<path>.safetensors`` + ``<path>.json``), in eval mode,
    its checkpoint metadata in ``.metadata``."""
    from safetensors.torch import load_file

    weights, meta = checkpoint_pair(path)
    if not meta.exists():
        raise FileNotFoundError(f"no pruner config at {meta} (expected <path>.json next to <path>.safetensors)")
    doc = json.loads(meta.read_text())
    if doc.get("format") != "tts-pruner-v1":
        raise ValueError(f"{meta} is not a tts pruner checkpoint (format {doc.get('format')!r})")
    cfg = doc["config"]
    cfg["directions"] = tuple(cfg["directions"])
    pruner = build_pruner(PrunerConfig(**cfg))
    pruner.load_state_dict(load_file(str(weights)))
    pruner.metadata = doc.get("metadata", {})
    return pruner.eval()


# -------------------------------------------------------------------- warm start from a schedule
def distill_schedule(pruner: PrunerModule, memory: torch.Tensor, grid: torch.Tensor, steps: int = 200,
                     lr: float = 1e-3, batch: int = 64, seed: int = 0) -> float:
    """Fit the pruner's logits to a static decision grid [K, nb] (e.g. a searched schedule) by
    cross-entropy on condition memories [N, K, Tc, D]: a cheap warm start (no sampler in the loop)
    before the straight-through training adapts the decisions per observation. Returns the final
    agreement (fraction of (k, b) whose argmax equals the grid)."""
    codes = pruner.config.codes
    unknown = sorted(set(grid.unique().tolist()) - set(codes))
    if unknown:
        raise ValueError(f"the schedule uses decision codes {unknown} the pruner has no option for ({codes})")
    target = torch.tensor([codes.index(c) for c in grid.flatten().tolist()]).reshape(grid.shape)  # [K, nb]
    opt = torch.optim.Adam(pruner.parameters(), lr=lr)
    g = torch.Generator().manual_seed(seed)
    was = pruner.training
    pruner.train()
    for _ in range(steps):
        idx = torch.randint(0, memory.shape[0], (min(batch, memory.shape[0]),), generator=g)
        logits = pruner(memory[idx])  # [b, K, nb, O]
        loss = nn.functional.cross_entropy(logits[:, 1:].reshape(-1, logits.shape[-1]),
                                           target[1:].expand(len(idx), -1, -1).reshape(-1))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    pruner.eval()
    with torch.no_grad():
        agree = (pruner(memory[:batch]).argmax(-1)[:, 1:] == target[1:]).float().mean()
    pruner.train(was)
    return float(agree)


# -------------------------------------------------------------------- training objective
def pruner_loss(pred: torch.Tensor, target: torch.Tensor, gates: torch.Tensor, sparsity: float,
                lam: float = 1.0, weight: Optional[torch.Tensor] = None) -> dict[str, torch.Tensor]:
    """The training objective: L1 between the sparse and the dense action (full horizon) plus
    ``lam`` * |per-sample reuse fraction - sparsity| (hard STE gates). ``weight`` [B] masks padded
    samples. Returns loss, l1, sparsity term and the per-sample reuse fraction."""
    from .gates import reuse_fraction

    B = pred.shape[0]
    w = torch.ones(B, device=pred.device) if weight is None else weight.to(pred.device)
    denom = w.sum().clamp_min(1.0)
    l1 = ((pred - target).abs().reshape(B, -1).mean(1) * w).sum() / denom
    reuse = reuse_fraction(gates)
    ls = ((reuse - sparsity).abs() * w).sum() / denom
    return {"loss": l1 + lam * ls, "l1": l1, "sparsity_loss": ls, "reuse": reuse}
