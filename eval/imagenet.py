"""Class-conditional DiT sampling, dense or accelerated, into an ADM-compatible ``.npz`` (+ FID/sFID).

    accelerate launch [--num_processes N] eval/imagenet.py --model PATH \
        --method dense|fora|taylorseer|toca|duca|uniform|static|tts|diffusers_fbc|diffusers_taylorseer \
        [--sparsity 0.8] [--steps 50] [--cfg 1.5] [--num-samples 2000] [--out samples.npz] [--pruner PATH] \
        [--fora-n 5] [--ref REF] [--seed 0] [--batch 64]

Methods (all but ``diffusers_*`` in the tts engine; ``dense`` is the untouched model):
  dense    the model as is
  fora     ``tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(N, "timestep"))`` (FORA-style)
  taylorseer  FORA's interval with an order-``--taylor-order`` Taylor forecast of each reused branch
           (``forecast=O``, TaylorSeer-style)
  toca     ToCa-style token-wise refresh (:mod:`tts.tokens`): full compute every ``--fora-n`` steps, in
           between the MLP recomputes ``--fresh-ratio`` of its tokens (highest attention received at the
           last full step, plus staleness), attention reused; with ``--sparsity`` instead of
           ``--fresh-ratio``, the ratio that computes ``1 - sparsity`` of the branch MACs
  duca     DuCa-style: as toca, but tokens chosen by dissimilarity (no attention maps) and the steps in
           between alternate aggressive (reuse all) / conservative (token refresh)
  uniform  ``tts.plans.uniform(sparsity, "timestep")``: ``--sparsity`` of the (step, branch) decisions reuse
  static   a searched schedule (``--plan``, eval/search_static.py --model): BAC-style
  diffusers_fbc  diffusers' First Block Cache on the model converted to diffusers' DiTTransformer2DModel
           (tts.adapters.dit_diffusers, same function): ``--fbc-threshold``, or with ``--sparsity`` the
           threshold whose sparsity on a calibration batch (``--calib-seed``, never the evaluation's) is
           closest (its ceiling is (depth - 1) / depth: the first block always computes)
  diffusers_taylorseer  diffusers' TaylorSeer cache on the converted model, every block's attn1 and ff:
           full steps 0, then every ``--fora-n``-th from step 2 (diffusers' warm-up of 1 step),
           order ``--taylor-order``
  tts      a learned pruner (``--pruner``, see tts.Pruner): argmax decisions, or with ``--sparsity`` exactly
           that fraction reused per sample (exact-budget mode); it reads the DiT's condition memory
           (:meth:`DiT.condition_memory`, encoded once per sampling call)

Sampling (:func:`tts.adapters.dit.sample_dit`): DDIM (eta 0) with DiT's linear schedule, batched
classifier-free guidance [cond; uncond] on eps. Sample ``i`` has class ``i % num_classes`` and initial
noise seeded by ``(--seed, i)``, and every process samples a disjoint contiguous shard of indices, so the
samples do not depend on the number of processes (bit-identical when the batches line up, e.g. when
``--batch`` divides the shards; otherwise equal up to float round-off of batched matmuls). ``--model``:
a tts DiT (``.safetensors`` + ``.json``, e.g. from eval/train_dit.py) or an official
``DiT-XL-2-256x256.pt``, or a diffusers DiT folder (a ``DiTPipeline`` folder such as facebook/DiT-XL-2-256,
whose ``vae/`` is then the default ``--vae``, or its ``transformer/``); latent models need ``--vae`` (a local
diffusers AutoencoderKL folder, e.g. stabilityai/sd-vae-ft-ema), pixel models ([-1, 1], 1 or 3 channels) are converted directly.

Outputs (main process, atomically): ``--out`` with ``arr_0`` uint8 [N, H, W, 3] and ``arr_1`` int64 labels
(ADM's evaluator layout), and ``<out>.json`` with FID/sFID against ``--ref`` (eval/fid.py: an ADM
reference batch, an image .npz or a folder), sampling wall-clock and s/image, realised sparsity and MACs
(dense vs realised, summed over all processes; with a pruner, its MACs too) and provenance.

Multi-process on CPU: ``accelerate launch --cpu`` starts a single process (or needs MPI), so use the
torchrun-style launcher, ``accelerate launch --multi_gpu --num_processes 2 eval/imagenet.py ...``: with no
CUDA device the script selects the CPU (gloo) backend itself (``--cpu`` forces it on a GPU machine).
Each process uses ``--threads`` torch threads (default: torch's, which the launcher sets to 1).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import parse_args, provenance, write_json  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dit import DiT, load_dit, sample_dit  # noqa: E402
from tts.adapters.dit_diffusers import DiffusersCache, DiffusersDiT, calibrate_fbc_threshold  # noqa: E402
from tts.io import atomic_path  # noqa: E402

METHODS = ("dense", "fora", "taylorseer", "toca", "duca", "uniform", "static", "tts", "diffusers_fbc",
           "diffusers_taylorseer")
CALIBRATION_IMAGES = 32
SD_VAE_SCALE = 0.18215  # latent scale of the Stable Diffusion VAE that DiT was trained with


# ------------------------------------------------------------------------------------------- helpers
def shard(num_samples: int, num_processes: int, rank: int) -> range:
    """The contiguous block of sample indices of process ``rank`` (sizes differ by at most one)."""
    return range(rank * num_samples // num_processes, (rank + 1) * num_samples // num_processes)


def index_seed(seed: int, index: int) -> int:
    """Seed of sample ``index``'s initial noise: a hash of (seed, index), independent of the process count."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1, np.uint64)[0])


def sample_noise(seed: int, indices: Sequence[int], shape: tuple[int, ...]) -> torch.Tensor:
    """Initial noise [len(indices), *shape], each row from its own (seed, index) generator."""
    return torch.stack([torch.randn(shape, generator=torch.Generator().manual_seed(index_seed(seed, i)))
                        for i in indices])


def to_uint8_rgb(images: torch.Tensor) -> torch.Tensor:
    """Model-space images [B, C, H, W] in [-1, 1] (C = 1 or 3) -> uint8 RGB [B, H, W, 3]."""
    if images.dim() != 4 or images.shape[1] not in (1, 3):
        raise ValueError(f"expected images [B, 1 or 3, H, W] in [-1, 1], got {tuple(images.shape)} "
                         "(a latent model needs --vae to decode its samples)")
    x = ((images.float() + 1.0) * 127.5).round().clamp(0, 255).to(torch.uint8)
    if x.shape[1] == 1:
        x = x.expand(-1, 3, -1, -1)
    return x.permute(0, 2, 3, 1).contiguous().cpu()


def load_vae(path: str, device: torch.device):
    """A diffusers AutoencoderKL from a local folder (never downloaded)."""
    from diffusers import AutoencoderKL

    p = Path(path)
    if not (p / "config.json").is_file():
        raise FileNotFoundError(
            f"no diffusers VAE at {p}: download stabilityai/sd-vae-ft-ema (or sd-vae-ft-mse) as a diffusers "
            "folder (config.json + diffusion_pytorch_model.safetensors) and pass --vae FOLDER")
    return AutoencoderKL.from_pretrained(str(p), local_files_only=True).to(device).eval()


def build_accelerator(model: DiT, args: argparse.Namespace) -> Any:
    """The tts accelerator of ``--method`` (None for dense); for ``diffusers_*`` a
    :class:`~tts.adapters.dit_diffusers.DiffusersCache` on a converted copy (sample ``acc.model``)."""
    if args.method == "dense":
        return None
    if args.method.startswith("diffusers_"):
        return build_diffusers_cache(model, args)
    if args.method == "fora":
        return tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(args.fora_n, "timestep"))
    if args.method == "taylorseer":  # FORA's interval with an order-O Taylor forecast of every reused branch
        return tts.accelerate(model, ("timestep",), plan=tts.plans.every_n(args.fora_n, "timestep"),
                              forecast=args.taylor_order)
    if args.method in ("toca", "duca"):
        make = tts.tokens.toca if args.method == "toca" else tts.tokens.duca
        return tts.accelerate(model, ("timestep",), plan=make(args.fora_n, fresh_ratio(model, args)))
    forecast = getattr(args, "forecast", 0)
    if args.method == "static":  # a searched schedule (eval/search_static.py --model ...)
        doc = json.loads(Path(args.plan).read_text())
        return tts.accelerate(model, tuple(doc["directions"]), plan=tts.plans.from_tensor(doc["grid"]),
                              forecast=forecast)
    if args.method == "uniform":
        return tts.accelerate(model, ("timestep",), plan=tts.plans.uniform(args.sparsity, "timestep"))
    pruner = tts.load_pruner(args.pruner)
    if pruner.config.memory_dim != model.config.hidden_size:
        raise ValueError(f"pruner {args.pruner} reads memory of width {pruner.config.memory_dim}, this DiT's "
                         f"condition memory has width {model.config.hidden_size}: it belongs to another model")
    return tts.accelerate(model, pruner.config.directions, pruner=pruner, sparsity=args.sparsity, forecast=forecast)


def build_diffusers_cache(model: DiT, args: argparse.Namespace) -> DiffusersCache:
    wrapped = model if isinstance(model, DiffusersDiT) else DiffusersDiT.from_dit(model)
    if args.method == "diffusers_taylorseer":
        return DiffusersCache(wrapped, "taylorseer", interval=args.fora_n, order=args.taylor_order, warmup=1)
    threshold = args.fbc_threshold
    if threshold is None:
        idx = range(CALIBRATION_IMAGES)
        labels = torch.tensor([i % model.config.num_classes for i in idx], device=model.pos_embed.device)
        noise = sample_noise(args.calib_seed, idx, (model.in_channels, model.config.input_size,
                                                   model.config.input_size))
        threshold, reached = calibrate_fbc_threshold(wrapped, args.sparsity, labels, noise, steps=args.steps,
                                                     cfg_scale=args.cfg)
        args.fbc_calibration = {"threshold": threshold, "sparsity": reached, "seed": args.calib_seed,
                                "images": CALIBRATION_IMAGES}
    return DiffusersCache(wrapped, "fbc", threshold=threshold)


def is_diffusers_cache(acc: Any) -> bool:
    return isinstance(acc, DiffusersCache)


def sampler_of(model: DiT, acc: Any):
    """The module to sample: the converted copy for a diffusers cache, else ``model``."""
    return acc.model if is_diffusers_cache(acc) else model


def describe(acc: Any) -> str:
    return acc.describe() if is_diffusers_cache(acc) else acc.plan.describe()


def last_call_counts(acc: Any) -> dict[str, float]:
    """decisions, reused, macs_dense, macs_realised, macs_pruner of ``acc``'s last sampling call."""
    if is_diffusers_cache(acc):
        call = acc.last_call()
        decisions = 2 * acc.depth * call.forwards
        return dict(decisions=decisions, reused=decisions - call.computed,
                    macs_dense=call.macs_dense(), macs_realised=call.macs, macs_pruner=0.0)
    summary = acc.summary()
    call = summary.calls[-1]
    d = call.decisions()
    dense, realised = summary.macs(call)
    return dict(decisions=d.numel(), reused=int((d != tts.plans.COMPUTE).sum()), macs_dense=dense,
                macs_realised=realised, macs_pruner=call.pruner_macs)


def mlp_share(model: DiT) -> float:
    """Share of a DiT block's branch MACs in its MLP (the token-wise branch): per token the MLP costs
    2 * D * mlp_hidden, attention 4 * D^2 (qkv, proj) + 2 * N * D (scores, weighted sum)."""
    cfg = model.config
    D, N = cfg.hidden_size, (cfg.input_size // cfg.patch_size) ** 2
    mlp = 2 * D * int(D * cfg.mlp_ratio)
    return mlp / (mlp + 4 * D * D + 2 * N * D)


def fresh_ratio(model: DiT, args: argparse.Namespace) -> float:
    """``--fresh-ratio``, or the one that matches ``--sparsity`` (of the branch MACs) at ``--fora-n``."""
    if args.fresh_ratio is not None:
        return args.fresh_ratio
    return tts.tokens.fresh_ratio_for(args.sparsity, args.fora_n, mlp_share(model), alternate=args.method == "duca")


def check_args(args: argparse.Namespace) -> None:
    if args.method == "uniform" and args.sparsity is None:
        raise ValueError("--method uniform needs --sparsity")
    if args.method == "tts" and not args.pruner:
        raise ValueError("--method tts needs --pruner PATH (a trained tts.Pruner)")
    if args.method == "static" and not args.plan:
        raise ValueError("--method static needs --plan SCHEDULE.json")
    if args.method in ("toca", "duca") and (args.sparsity is None) == (args.fresh_ratio is None):
        raise ValueError(f"--method {args.method} needs exactly one of --fresh-ratio and --sparsity")
    if args.fresh_ratio is not None and args.method not in ("toca", "duca"):
        raise ValueError("--fresh-ratio is only used by --method toca / duca")
    fbc_threshold = getattr(args, "fbc_threshold", None)
    if args.method == "diffusers_fbc" and (args.sparsity is None) == (fbc_threshold is None):
        raise ValueError("--method diffusers_fbc needs exactly one of --fbc-threshold and --sparsity")
    if fbc_threshold is not None and args.method != "diffusers_fbc":
        raise ValueError("--fbc-threshold is only used by --method diffusers_fbc")
    if args.method == "diffusers_fbc" and args.sparsity is not None and args.calib_seed == args.seed:
        raise ValueError("--calib-seed must differ from --seed (never calibrate on the evaluation's noise)")
    if args.method in ("dense", "fora", "taylorseer", "static", "diffusers_taylorseer") and args.sparsity is not None:
        raise ValueError(f"--sparsity does not apply to --method {args.method}")
    if args.pruner and args.method != "tts":
        raise ValueError("--pruner is only used by --method tts")
    if getattr(args, "forecast", 0) and args.method not in ("static", "tts"):
        raise ValueError("--forecast applies to --method static / tts (taylorseer has --taylor-order)")
    if args.method in ("fora", "taylorseer", "toca", "duca", "diffusers_taylorseer") and args.fora_n < 1:
        raise ValueError("--fora-n must be >= 1")
    for name in ("num_samples", "batch", "steps"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
    if args.out.suffix != ".npz":
        raise ValueError(f"--out must end with .npz, got {args.out}")


class Meter:
    """Per-process totals of decisions and MACs over the sampling calls of an accelerator."""

    def __init__(self) -> None:
        self.images = 0
        self.calls = 0
        self.decisions = 0
        self.reused = 0
        self.macs_dense = 0.0
        self.macs_realised = 0.0
        self.macs_pruner = 0.0
        self.sample_s = 0.0

    def add_call(self, acc: Optional["tts.Accelerator"], images: int, seconds: float) -> None:
        self.images += images
        self.calls += 1
        self.sample_s += seconds
        if acc is None:
            return
        c = last_call_counts(acc)
        self.decisions += c["decisions"]
        self.reused += c["reused"]
        self.macs_dense += c["macs_dense"]
        self.macs_realised += c["macs_realised"]
        self.macs_pruner += c["macs_pruner"]


def dense_macs_per_image(model: DiT, steps: int, cfg: float) -> float:
    """MACs of one image's sampling call with the untouched model (rows x steps forwards, embedders
    excluded as in the engine's count), by torch's FlopCounterMode."""
    from tts.flops import flop_counter_macs

    p = model.pos_embed
    size = model.config.input_size
    x = torch.zeros(1, model.in_channels, size, size, device=p.device, dtype=p.dtype)
    t = torch.zeros(1, dtype=torch.long, device=p.device)
    c = torch.zeros(1, model.config.hidden_size, device=p.device, dtype=p.dtype)
    with torch.no_grad():
        one = flop_counter_macs(lambda: model(x, t, t, c=c))
    return float(one * steps * (2 if cfg != 1.0 else 1))


# ---------------------------------------------------------------------------------------------- main
def main(argv: Optional[Sequence[str]] = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, help="tts DiT (<path>.safetensors + .json), an official DiT .pt or a "
                                                   "diffusers DiT folder (DiTPipeline or its transformer/)")
    ap.add_argument("--config", default=None, help="DIT_CONFIGS name for an official .pt (e.g. DiT-XL/2); default: "
                                                    "inferred from the tensor shapes")
    ap.add_argument("--vae", default=None, help="local diffusers AutoencoderKL folder (latent DiTs)")
    ap.add_argument("--method", choices=METHODS, default="dense")
    ap.add_argument("--sparsity", type=float, default=None,
                    help="uniform: fraction of reused decisions; tts: exact-budget mode (default: argmax)")
    ap.add_argument("--pruner", default=None, help="trained tts.Pruner (<path>.safetensors + .json), --method tts")
    ap.add_argument("--fora-n", type=int, default=5, help="fora / taylorseer / toca / duca: compute every N-th step")
    ap.add_argument("--fresh-ratio", type=float, default=None,
                    help="toca / duca: fraction of MLP tokens recomputed at a refresh step (or give --sparsity)")
    ap.add_argument("--taylor-order", type=int, default=1, help="taylorseer / diffusers_taylorseer: forecast order O")
    ap.add_argument("--fbc-threshold", type=float, default=None, help="diffusers_fbc: FBCache threshold")
    ap.add_argument("--calib-seed", type=int, default=1,
                    help="diffusers_fbc with --sparsity: noise seed of the threshold calibration batch")
    ap.add_argument("--plan", default=None, help="static: a searched schedule JSON (eval/search_static.py)")
    ap.add_argument("--forecast", type=int, default=0,
                    help="static / tts: TaylorSeer-style forecast of order O for timestep reuse (0 = plain reuse)")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--cfg", type=float, default=1.5, help="classifier-free guidance scale (1 = none)")
    ap.add_argument("--scheduler", choices=("ddim", "ddpm"), default="ddim",
                    help="ddpm's step noise depends on the batch composition (not per index)")
    ap.add_argument("--num-samples", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=64, help="images per sampling call and process")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("samples.npz"))
    ap.add_argument("--ref", default=None, help="FID reference: ADM reference batch / stats .npz, image .npz or folder")
    ap.add_argument("--ref-cache", default=None, help="cache for reference stats computed from images (.npz)")
    ap.add_argument("--inception", default=None, help="FID Inception weights (see eval/fid.py)")
    ap.add_argument("--fid-batch", type=int, default=50)
    ap.add_argument("--cpu", action="store_true", help="run on CPU even if CUDA is available")
    ap.add_argument("--no-progress", action="store_true")
    args = parse_args(ap, argv)
    check_args(args)

    model = load_dit(args.model, config=args.config)  # clear FileNotFoundError before any process group starts
    if args.vae is None and getattr(model, "vae_path", None):  # a DiTPipeline folder with its vae/
        args.vae = model.vae_path
    if args.vae is None and model.in_channels not in (1, 3):
        raise ValueError(f"{args.model} is a latent DiT ({model.in_channels} channels): pass --vae FOLDER "
                         "(diffusers AutoencoderKL, e.g. stabilityai/sd-vae-ft-ema) to decode its samples")

    from accelerate import Accelerator
    from accelerate.utils import gather_object

    accelerator = Accelerator(cpu=args.cpu or not torch.cuda.is_available())
    rank, world, main_proc = accelerator.process_index, accelerator.num_processes, accelerator.is_main_process
    device = accelerator.device
    model = model.to(device)
    vae = load_vae(args.vae, device) if args.vae else None
    acc = build_accelerator(model, args)
    sampler = sampler_of(model, acc)

    num_classes = model.config.num_classes
    size = model.config.input_size
    mine = shard(args.num_samples, world, rank)
    longest = max(len(shard(args.num_samples, world, r)) for r in range(world))
    rounds = math.ceil(longest / args.batch)  # every process takes part in every gather
    meter = Meter()
    collected: list[torch.Tensor] = []
    collected_idx: list[torch.Tensor] = []
    H = W = None
    accelerator.wait_for_everyone()
    t_start = time.perf_counter()
    bar = tqdm(total=args.num_samples, desc=f"sample {args.method}", disable=not main_proc or args.no_progress)
    for r in range(rounds):
        idx = list(mine[r * args.batch:(r + 1) * args.batch])
        if idx:
            labels = torch.tensor([i % num_classes for i in idx], device=device)
            noise = sample_noise(args.seed, idx, (model.in_channels, size, size))
            gen = torch.Generator(device="cpu").manual_seed(index_seed(args.seed, idx[0]))  # ddpm step noise
            t0 = time.perf_counter()
            x = sample_dit(sampler, labels, steps=args.steps, cfg_scale=args.cfg, noise=noise, generator=gen,
                           scheduler=args.scheduler)
            if vae is not None:
                with torch.no_grad():
                    x = vae.decode(x / SD_VAE_SCALE).sample
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            meter.add_call(acc, len(idx), time.perf_counter() - t0)
            images = to_uint8_rgb(x)
            H, W = images.shape[1], images.shape[2]
        # pad to a fixed size so that every process contributes an equal block to the gather
        H, W = _agree_shape(accelerator, H, W) if r == 0 else (H, W)
        block = torch.zeros(args.batch, H, W, 3, dtype=torch.uint8)
        index = torch.full((args.batch,), -1, dtype=torch.long)
        if idx:
            block[:len(idx)] = images
            index[:len(idx)] = torch.tensor(idx)
        all_images = accelerator.gather(block.to(device)).cpu()
        all_index = accelerator.gather(index.to(device)).cpu()
        if main_proc:
            keep = all_index >= 0
            collected.append(all_images[keep])
            collected_idx.append(all_index[keep])
            bar.update(int(keep.sum()))
    bar.close()
    accelerator.wait_for_everyone()
    wall = time.perf_counter() - t_start
    meters = gather_object([vars(meter)])
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        # the last collective: tear gloo down before a process exits (an open group aborted rank 1
        # at interpreter exit, "terminate called without an active exception", under load)
        torch.distributed.destroy_process_group()
    if acc is not None:
        plan_desc = describe(acc)
        acc.remove()
    else:
        plan_desc = "dense (untouched model)"
    if not main_proc:
        return {}

    order = torch.cat(collected_idx).argsort()
    arr = torch.cat(collected)[order].numpy()
    indices = torch.cat(collected_idx)[order].numpy()
    if not np.array_equal(indices, np.arange(args.num_samples)):
        raise RuntimeError("gathered sample indices are not 0..N-1 (a process did not take part in every gather)")
    labels_all = indices % num_classes
    with atomic_path(args.out, ".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, arr_0=arr, arr_1=labels_all.astype(np.int64))

    total = {k: sum(m[k] for m in meters) for k in meters[0]}
    result: dict[str, Any] = {
        "model": str(args.model),
        "model_config": dataclasses.asdict(model.config),
        "model_checkpoint": getattr(model, "checkpoint_info", None),
        "method": args.method,
        "plan": plan_desc,
        "sparsity_target": args.sparsity,
        "fora_n": args.fora_n if args.method in ("fora", "taylorseer", "toca", "duca", "diffusers_taylorseer") else None,
        "taylor_order": args.taylor_order if args.method in ("taylorseer", "diffusers_taylorseer") else None,
        "forecast": args.forecast,
        "fresh_ratio": getattr(getattr(acc, "plan", None), "fresh_ratio", None),
        "fbc_threshold": acc.config.threshold if args.method == "diffusers_fbc" else None,
        "fbc_calibration": getattr(args, "fbc_calibration", None),
        "pruner": args.pruner,
        "steps": args.steps,
        "scheduler": args.scheduler,
        "cfg_scale": args.cfg,
        "num_samples": args.num_samples,
        "batch_per_process": args.batch,
        "num_processes": world,
        "distributed_type": str(accelerator.distributed_type),
        "device": str(device),
        "samples": str(args.out),
        "image_shape": list(arr.shape[1:]),
        "sampling_wall_s": wall,
        "s_per_image": wall / args.num_samples,
        "sampling_s_per_process": [m["sample_s"] for m in meters],
        "s_per_image_per_process": [m["sample_s"] / max(m["images"], 1) for m in meters],
    }
    if acc is not None:
        dense, realised, pruner_macs = total["macs_dense"], total["macs_realised"], total["macs_pruner"]
        result.update(
            sparsity=total["reused"] / max(total["decisions"], 1),
            decisions=total["decisions"],
            macs_dense_per_image=dense / args.num_samples,
            macs_realised_per_image=realised / args.num_samples,
            macs_pruner_per_image=pruner_macs / args.num_samples,
            macs_ratio=dense / max(realised, 1.0),
            macs_ratio_with_pruner=dense / max(realised + pruner_macs, 1.0),
        )
    else:
        per_image = dense_macs_per_image(model, args.steps, args.cfg)
        result.update(sparsity=0.0, macs_dense_per_image=per_image, macs_realised_per_image=per_image,
                      macs_pruner_per_image=0.0, macs_ratio=1.0, macs_ratio_with_pruner=1.0)
    if args.ref:
        import fid

        if device.type == "cpu" and args.threads is None:  # the other processes are done: use every core
            torch.set_num_threads(os.cpu_count() or 1)
        t0 = time.perf_counter()
        inception = fid.load_inception(args.inception, device=str(device))
        progress = not args.no_progress
        ref = fid.reference_stats(args.ref, cache=args.ref_cache, model=inception, batch_size=args.fid_batch,
                                  progress=progress)
        result.update(fid.fid_sfid(arr, ref, model=inception, batch_size=args.fid_batch, progress=progress))
        result.update(ref=str(args.ref), inception=getattr(inception, "weights_source", None),
                      fid_seconds=time.perf_counter() - t0)
    result["provenance"] = provenance(seeds={"noise": args.seed, "per_sample": "SeedSequence([seed, index])",
                                             "labels": "index % num_classes"})
    json_path = args.out.with_suffix(".json")
    write_json(json_path, result)
    summary = {k: result[k] for k in ("method", "sparsity", "macs_ratio", "s_per_image", "fid", "sfid") if k in result}
    print(f"wrote {args.out} {tuple(arr.shape)} and {json_path}: {summary}")
    return result


def _agree_shape(accelerator, H: Optional[int], W: Optional[int]) -> tuple[int, int]:
    """Image size known to every process (a process without samples in round 0 learns it from the others)."""
    from accelerate.utils import gather_object

    shapes = [s for s in gather_object([(H, W)]) if s[0] is not None]
    if not shapes:
        raise RuntimeError("no process produced samples")
    return shapes[0]


if __name__ == "__main__":
    try:
        main()
    except (FileNotFoundError, ValueError) as e:
        sys.exit(f"error: {e}")
