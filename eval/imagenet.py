"""Class-conditional DiT sampling, dense or accelerated, into an ADM-compatible ``.npz`` (+ FID/sFID).

    accelerate launch [--num_processes N] eval/imagenet.py --model PATH --method METHOD \
        [--steps 50] [--cfg 1.5] [--num-samples 2000] [--out samples.npz] [--ref REF] [--seed 0] [--batch 64]

``--method`` takes the vocabulary of both suites (eval/common/methods.py), e.g. ``dense``, ``ddim:10``,
``every_n:5:timestep`` (FORA), ``taylorseer:5:2``, ``toca:6@0.8`` (ToCa-style token refresh at 80% of
the branch MACs reused), ``duca:6@0.8``, ``uniform:0.8:timestep``, ``file:SCHEDULE.json`` (a searched
schedule, eval/search_static.py --model), ``pruner:PATH@0.8`` (a learned pruner, exact budget; it reads
the DiT's condition memory, encoded once per sampling call), ``diffusers:fbc@0.8`` (diffusers' First
Block Cache on the model converted to ``DiTTransformer2DModel``, its threshold calibrated to that
sparsity on ``--calib-seed`` noise; its ceiling is (depth - 1) / depth), ``diffusers:taylorseer:5:2``.
All but ``diffusers:`` run in the tts engine; ``dense`` is the untouched model; ``ddim:K`` samples the
untouched model with K steps instead of ``--steps``.

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

from common.methods import IMAGE_KINDS, VOCABULARY, Method, parse_method  # noqa: E402
from image_suite.sampling import (SD_VAE_SCALE, Meter, build_accelerator, dense_macs_per_image,  # noqa: E402
                                  describe, index_seed, load_vae, sample_noise, sampler_of, sampler_steps, shard,
                                  to_uint8_rgb)
from tts.adapters.dit import load_dit, sample_dit  # noqa: E402
from tts.io import atomic_path  # noqa: E402


def check_args(args: argparse.Namespace, method: Method) -> None:
    if method.kind == "diffusers" and method.cache == "fbc" and method.sparsity is not None \
            and args.calib_seed == args.seed:
        raise ValueError("--calib-seed must differ from --seed (never calibrate on the evaluation's noise)")
    for name in ("num_samples", "batch", "steps"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
    if args.out.suffix != ".npz":
        raise ValueError(f"--out must end with .npz, got {args.out}")


# ---------------------------------------------------------------------------------------------- main
def main(argv: Optional[Sequence[str]] = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, help="tts DiT (<path>.safetensors + .json), an official DiT .pt or a "
                                                   "diffusers DiT folder (DiTPipeline or its transformer/)")
    ap.add_argument("--config", default=None, help="DIT_CONFIGS name for an official .pt (e.g. DiT-XL/2); default: "
                                                    "inferred from the tensor shapes")
    ap.add_argument("--vae", default=None, help="local diffusers AutoencoderKL folder (latent DiTs)")
    ap.add_argument("--method", default="dense", help=f"one of: {VOCABULARY}")
    ap.add_argument("--calib-seed", type=int, default=1,
                    help="diffusers:fbc@RHO: noise seed of the threshold calibration batch")
    ap.add_argument("--forecast", type=int, default=0,
                    help="file: / pruner: methods: Taylor forecast of order O for timestep reuse (0 = plain reuse)")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--cfg", type=float, default=1.5, help="classifier-free guidance scale (1 = none)")
    ap.add_argument("--scheduler", choices=("ddim", "ddpm", "dpm"), default="ddim",
                    help="the base sampler (dpm: DPM-Solver++); ddpm's step noise depends on the batch "
                         "composition (not per index)")
    ap.add_argument("--num-samples", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=64, help="images per sampling call and process")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("samples.npz"))
    ap.add_argument("--ref", default=None, help="FID reference: ADM reference batch / stats .npz, image .npz or folder")
    ap.add_argument("--ref-cache", default=None, help="cache for reference stats computed from images (.npz)")
    ap.add_argument("--inception", default=None, help="FID Inception weights (see eval/fid.py)")
    ap.add_argument("--fid-batch", type=int, default=50)
    ap.add_argument("--fid-bootstrap", type=int, default=50,
                    help="resamples of the FID's 95%% bootstrap interval over the samples (0: none)")
    ap.add_argument("--cpu", action="store_true", help="run on CPU even if CUDA is available")
    ap.add_argument("--no-progress", action="store_true")
    args = parse_args(ap, argv)
    method = parse_method(args.method, kinds=IMAGE_KINDS, forecast=args.forecast)
    if method.kind in ("ddim", "dpm") and method.sampler.spacing is not None:
        ap.error(f"{args.method}: the image suite spaces timesteps as DiT does (leading); drop the spacing")
    args.steps, args.scheduler = sampler_steps(method, args.steps, args.scheduler)
    check_args(args, method)

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
    calibration: dict[str, Any] = {}
    acc = build_accelerator(model, method, steps=args.steps, cfg=args.cfg, calib_seed=args.calib_seed,
                            calibration=calibration)
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
    bar = tqdm(total=args.num_samples, desc=f"sample {method.label}", disable=not main_proc or args.no_progress)
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
        "method": method.label,
        "method_spec": args.method,
        "plan": plan_desc,
        "sparsity_target": method.sparsity,
        "interval": method.n if method.kind not in ("ddim", "dpm") else None,
        "taylor_order": method.order or None,
        "forecast": args.forecast,
        "fresh_ratio": getattr(getattr(acc, "plan", None), "fresh_ratio", None),
        "fbc_threshold": acc.config.threshold if method.cache == "fbc" else None,
        "fbc_calibration": calibration or None,
        "pruner": str(method.path) if method.kind == "pruner" else None,
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
        from image_suite import fid

        if device.type == "cpu" and args.threads is None:  # the other processes are done: use every core
            torch.set_num_threads(os.cpu_count() or 1)
        t0 = time.perf_counter()
        inception = fid.load_inception(args.inception, device=str(device))
        progress = not args.no_progress
        ref = fid.reference_stats(args.ref, cache=args.ref_cache, model=inception, batch_size=args.fid_batch,
                                  progress=progress)
        result.update(fid.fid_sfid(arr, ref, model=inception, batch_size=args.fid_batch, progress=progress,
                                   bootstrap=args.fid_bootstrap))
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
