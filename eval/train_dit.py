"""Train a small class-conditional pixel-space DiT on scikit-learn's digits (8x8, 10 classes), on CPU.

    python eval/train_dit.py --out checkpoints/digits_dit --threads 2            # full run (see below)
    python eval/train_dit.py --out checkpoints/digits_dit --resume               # continue after an interruption
    python eval/train_dit.py --out checkpoints/digits_dit --stop-at 500          # save the state at step 500 and stop
    python eval/train_dit.py --benchmark 5 --threads 1                           # time a few steps, no training
    python eval/train_dit.py --export-ref data/digits16.npz                      # the data as an FID reference

Data: ``sklearn.datasets.load_digits`` (1797 gray 8x8 images, values 0..16, bundled with scikit-learn,
no download), bilinearly upsampled to ``--size`` (16) and scaled to [-1, 1], 1 channel; optional random
horizontal shifts (``--shift`` pixels, background-padded). ``--export-ref`` writes the same images as an
ADM-style uint8 RGB npz (``arr_0`` [N, H, W, 3], ``arr_1`` labels) for ``eval/imagenet.py --ref``.

Model: the official-layout DiT (tts.adapters.dit) with DiTConfig(input_size=16, patch_size=2,
in_channels=1, hidden_size=128, depth=6, num_heads=4, num_classes=10, learn_sigma=False): 64 tokens, 12
prunable branches per step, 1.87 M parameters. Objective: DDPM epsilon MSE with DiT's linear schedule
(betas 1e-4..0.02, 1000 steps, diffusers ``DDPMScheduler.add_noise``), class dropout 0.1 (the null
class used for classifier-free guidance), AdamW (lr 3e-4, no weight decay, 100 warm-up steps then
cosine), grad-norm clip 1, EMA of the weights (decay min(0.999, (1 + n) / (10 + n))), batch 128.

Size: hidden 128 keeps the default 2000 steps (142 epochs) at about 20-30 min on 2 CPU cores (one
step at batch 128 takes about 1 s on one thread; hidden 192 takes 1.6x longer).

Resumable: the full training state (model, EMA, optimiser, LR schedule, RNG states, data generator,
losses) is written atomically every ``--save-every`` steps to ``runs/<out name>/state.pt`` and at the
end; ``--resume`` continues from it exactly (same batches and noise as an uninterrupted run). The final
EMA weights are written atomically as ``<out>.safetensors`` + ``<out>.json`` (config and provenance:
command, git SHA, machine, seed, steps, loss).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import parse_args, provenance  # noqa: E402
from common.model_training import EMA, restore_training_state, save_training_state  # noqa: E402

from tts.adapters.dit import DIT_BETAS, DiT, DiTConfig, save_dit  # noqa: E402
from tts.io import atomic_path  # noqa: E402

STATE_FORMAT = "tts-train-dit-state-v1"


def digits_dataset(size: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """scikit-learn's digits as images [1797, 1, size, size] in [-1, 1] and labels [1797] (int64)."""
    try:
        from sklearn.datasets import load_digits
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("the digits data set comes with scikit-learn: pip install scikit-learn") from e
    digits = load_digits()
    x = torch.from_numpy(digits.images.astype(np.float32) / 16.0).unsqueeze(1)  # [N, 1, 8, 8] in [0, 1]
    if size != 8:
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)
    x = x.clamp(0, 1) * 2 - 1
    return x.contiguous(), torch.from_numpy(digits.target.astype(np.int64))


def export_reference(path: Path, size: int) -> None:
    """The training images as an ADM-style npz (uint8 RGB ``arr_0``, labels ``arr_1``), atomically."""
    x, y = digits_dataset(size)
    img = ((x + 1) * 127.5).round().clamp(0, 255).to(torch.uint8).expand(-1, 3, -1, -1).permute(0, 2, 3, 1)
    with atomic_path(path, ".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, arr_0=img.numpy(), arr_1=y.numpy())
    print(f"wrote {path}: {tuple(img.shape)} uint8")


def random_shift(x: torch.Tensor, max_shift: int, generator: torch.Generator) -> torch.Tensor:
    """Shift each image horizontally by an integer in [-max_shift, max_shift], filling with background (-1)."""
    if max_shift <= 0:
        return x
    W = x.shape[-1]
    shifts = torch.randint(-max_shift, max_shift + 1, (x.shape[0],), generator=generator)
    cols = torch.arange(W)[None, :] - shifts[:, None]  # source column of each output column
    valid = (cols >= 0) & (cols < W)
    idx = cols.clamp(0, W - 1)[:, None, None, :].expand_as(x)
    out = torch.gather(x, -1, idx)
    return torch.where(valid[:, None, None, :], out, torch.full_like(out, -1.0))


def build_config(args: argparse.Namespace) -> DiTConfig:
    return DiTConfig(input_size=args.size, patch_size=args.patch, in_channels=1, hidden_size=args.hidden,
                     depth=args.depth, num_heads=args.heads, mlp_ratio=4.0, class_dropout_prob=args.class_dropout,
                     num_classes=10, learn_sigma=False)


def main(argv: Optional[Sequence[str]] = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("checkpoints/digits_dit"), help="checkpoint path without suffix")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--warmup", type=int, default=100)
    ap.add_argument("--size", type=int, default=16, help="image size (digits are upsampled from 8x8)")
    ap.add_argument("--patch", type=int, default=2)
    ap.add_argument("--hidden", type=int, default=128)
    ap.add_argument("--depth", type=int, default=6)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--class-dropout", type=float, default=0.1)
    ap.add_argument("--ema", type=float, default=0.999)
    ap.add_argument("--shift", type=int, default=0, help="random horizontal shift augmentation (pixels)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run-dir", type=Path, default=None, help="resumable state (default: runs/<out name>)")
    ap.add_argument("--save-every", type=int, default=250)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                    help="save the state and stop at this step without writing the checkpoint (continue with --resume)")
    ap.add_argument("--benchmark", type=int, default=0, metavar="N",
                    help="time N training steps (after 2 warm-up steps), print s/step and the projected run time; "
                         "writes nothing")
    ap.add_argument("--export-ref", type=Path, default=None, help="write the data as an ADM-style npz and exit")
    args = parse_args(ap, argv)

    if args.export_ref is not None:
        export_reference(args.export_ref, args.size)
        return
    from diffusers import DDPMScheduler

    torch.manual_seed(args.seed)
    images, labels = digits_dataset(args.size)
    config = build_config(args)
    model = DiT(config)
    model.train()
    ema = EMA(model, lambda n: min(args.ema, (1 + n) / (10 + n)))
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, betas=(0.9, 0.999), weight_decay=0.0)
    warmup = max(1, min(args.warmup, args.steps // 10))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(s, args.steps) / args.steps)))
    noise_sched = DDPMScheduler(**DIT_BETAS)
    T = noise_sched.config.num_train_timesteps
    gen = torch.Generator().manual_seed(args.seed)
    run_dir = args.run_dir or Path("runs") / args.out.name
    state_path = run_dir / "state.pt"
    step, losses = 0, []

    if args.resume and not args.benchmark:
        if not state_path.exists():
            raise SystemExit(f"--resume: no saved state at {state_path}")
        st = torch.load(state_path, map_location="cpu", weights_only=False)  # our own file (RNG states)
        if st.get("format") != STATE_FORMAT or st["config"] != asdict(config):
            raise SystemExit(f"{state_path} was saved for another model config ({st.get('config')}); "
                             "use the same --size/--hidden/--depth/... or another --run-dir")
        step, losses = restore_training_state(st, "model", model, ema, opt, sched)
        gen.set_state(st["data_rng"])
        print(f"resumed from {state_path} at step {step}")

    def save_state() -> None:
        save_training_state(state_path, "model", model, ema, opt, sched, step, losses, format=STATE_FORMAT,
                            config=asdict(config), data_rng=gen.get_state(),
                            args={k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()})

    def train_step() -> float:
        idx = torch.randint(0, len(images), (args.batch,), generator=gen)
        x0 = random_shift(images[idx], args.shift, gen)
        y = labels[idx]
        t = torch.randint(0, T, (args.batch,), generator=gen)
        noise = torch.randn(x0.shape, generator=gen)
        xt = noise_sched.add_noise(x0, noise, t)
        loss = F.mse_loss(model(xt, t, y), noise)  # train mode: the label embedder drops classes (CFG)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        ema.update(model)
        return float(loss.detach())

    params = sum(p.numel() for p in model.parameters() if p.requires_grad)
    if args.benchmark:
        for _ in range(2):
            train_step()
        t0 = time.perf_counter()
        for _ in range(args.benchmark):
            train_step()
        per = (time.perf_counter() - t0) / args.benchmark
        print(f"{params / 1e6:.2f} M params, batch {args.batch}, {torch.get_num_threads()} thread(s): {per:.3f} s/step; "
              f"{args.steps} steps ~ {per * args.steps / 60:.1f} min")
        return

    t_run = time.perf_counter()
    with tqdm(total=args.steps, initial=step, desc=f"train {args.out.name}") as bar:
        while step < args.steps:
            losses.append(train_step())
            step += 1
            bar.update(1)
            if step % 25 == 0:
                bar.set_postfix(loss=f"{np.mean(losses[-100:]):.4f}", lr=f"{sched.get_last_lr()[0]:.2e}")
            if step % args.save_every == 0 or step == args.steps or step == args.stop_at:
                save_state()
            if step == args.stop_at:
                print(f"stopped at step {step}; state in {state_path} (continue with --resume)")
                return
    meta = provenance(seeds={"train": args.seed})
    meta.update(data="sklearn.datasets.load_digits (1797 8x8 digits, 10 classes)", image_size=args.size,
                pixel_range=[-1, 1], channels=1, steps=args.steps, steps_done=step, batch=args.batch, lr=args.lr,
                shift=args.shift, ema_decay=args.ema, params=params, objective="DDPM epsilon MSE, DiT linear schedule",
                final_loss=float(np.mean(losses[-200:])) if losses else None,
                train_seconds_this_run=time.perf_counter() - t_run, weights="EMA")
    save_dit(ema.model, args.out, metadata=meta)
    print(f"saved {args.out}.safetensors / .json (final loss {meta['final_loss']:.4f})")


if __name__ == "__main__":
    main()
