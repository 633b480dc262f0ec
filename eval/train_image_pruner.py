"""Train a TTS pruner for a class-conditional DiT (the image variant: forward and timestep directions).

    python eval/train_image_pruner.py --model checkpoints/digits_dit --out checkpoints/pruners/digits_tts_0.8 \
        --sparsity 0.8 --steps 50 --cfg 1.5 --n-train 256 --n-val 64 --epochs 4 [--prior SCHEDULE.json]

The pruner reads the DiT's own conditioning for all K steps at once (``DiT.condition_memory``:
timestep + class embedding; with guidance the batch is [cond; uncond], so the two halves get their
own decisions) and is trained on sampled trajectories of the dense model with paired noise: for
each training index i (class i % num_classes, initial noise seeded by ``(--seed + 2, i)``, disjoint
from eval/imagenet.py's evaluation samples, which use ``(0, i)``), the dense DDIM sample is the
target and the sparse sampler, run with straight-through gates from the same noise, is trained
towards it: L1 on the final sample + lambda * |reuse fraction - sparsity| per row. Validation uses
the test-time rule (``--val-mode``). Loop, checkpoints and ``--resume``: :func:`tts.training.fit`,
whose :class:`tts.training.PrunerTrainingConfig` field of the same name each shared option sets.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import parse_args  # noqa: E402
from common.training_args import add_training_args, exit_when_stopped, training_metadata  # noqa: E402
from image_suite.sampling import index_seed  # noqa: E402

import tts  # noqa: E402
from tts.adapters.dit import load_dit, sample_dit  # noqa: E402
from tts.gates import reuse_fraction  # noqa: E402
from tts.pruner import PrunerConfig, PrunerPlan, build_pruner  # noqa: E402
from tts.training import PrunerTrainingConfig, RecordingPlan, fit, read_grid  # noqa: E402


def noise_for(model, seed: int, indices) -> torch.Tensor:
    C, size = model.in_channels, model.config.input_size
    return torch.stack([torch.randn(C, size, size, generator=torch.Generator().manual_seed(index_seed(seed, int(i))))
                        for i in indices])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, required=True, help="the (frozen) DiT (tts.adapters.dit.load_dit)")
    add_training_args(ap, sparsity=0.8, directions="forward,timestep", batch=16)
    ap.add_argument("--steps", type=int, default=50, help="DDIM steps")
    ap.add_argument("--cfg", type=float, default=1.5)
    ap.add_argument("--n-train", type=int, default=256)
    ap.add_argument("--n-val", type=int, default=64)
    args = parse_args(ap, argv)
    try:
        config = PrunerTrainingConfig.from_dict(vars(args))
    except ValueError as e:
        ap.error(str(e))
    directions = config.directions
    if "rollout" in directions:
        raise SystemExit("an image generator has no rollouts: use the forward and/or timestep directions")
    torch.manual_seed(config.seed)
    model = load_dit(args.model).requires_grad_(False)
    n_cls = model.y_embedder.num_classes
    data_seed = config.seed + 2
    train_idx = np.arange(config.n_train)
    val_idx = np.arange(config.n_train, config.n_train + config.n_val)

    def dense(indices) -> torch.Tensor:
        out = []
        for s in range(0, len(indices), 64):
            idx = indices[s:s + 64]
            out.append(sample_dit(model, torch.as_tensor(idx % n_cls), steps=args.steps, cfg_scale=args.cfg,
                                  noise=noise_for(model, data_seed, idx)))
        return torch.cat(out)

    print(f"dense targets for {len(train_idx)} + {len(val_idx)} samples ...", flush=True)
    targets = dense(np.concatenate([train_idx, val_idx]))
    cfg = model.config
    pruner = build_pruner(PrunerConfig(memory_dim=cfg.hidden_size, num_branches=2 * cfg.depth, directions=directions,
                                       hidden=config.hidden, heads=config.heads, ffn=config.ffn, steps=args.steps,
                                       prior=config.prior is not None,
                                       tie_branches=config.tie_branches, step_query=config.step_query))
    if config.prior is not None:
        grid = read_grid(config.prior, steps=args.steps, branches=2 * cfg.depth, reuse=config.prior_reuse)
        pruner.set_prior(grid, margin=config.prior_margin)
    train_plan = PrunerPlan(pruner, mode="ste", sparsity=config.sparsity if config.train_budget else None,
                            autocast=config.autocast)

    def run(plan, idx, opt=None) -> dict:
        labels = torch.as_tensor(idx % n_cls)
        pred = sample_dit(model, labels, steps=args.steps, cfg_scale=args.cfg, noise=noise_for(model, data_seed, idx),
                          enable_grad=opt is not None)
        l1 = (pred - targets[idx]).abs().mean()
        if opt is not None:
            reuse = reuse_fraction(plan.gates)  # every row: cond and uncond halves
            loss = l1 + config.lam * (reuse - config.sparsity).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if config.clip_grad is not None:
                torch.nn.utils.clip_grad_norm_(pruner.parameters(), config.clip_grad)
            opt.step()
            reuse = reuse.detach()
        else:
            reuse = (plan.last_codes != 0).float().mean((1, 2))
        return {"l1": float(l1.detach()), "sparsity": float(reuse.mean()), "frames": len(idx)}

    def batches(idx, rng):
        order = idx if rng is None else rng.permutation(idx)
        return [order[s:s + config.batch] for s in range(0, len(order), config.batch)]

    def train_epoch(opt, rng, noise_rng, epoch, progress):  # short epochs: resumable per epoch only
        with tts.accelerate(model, directions, plan=train_plan, forecast=config.forecast):
            return [run(train_plan, b, opt) for b in tqdm(batches(train_idx, rng), desc=f"epoch {epoch + 1}/{config.epochs}")]

    def validate():
        plan = RecordingPlan(pruner, config.val_mode, config.sparsity)
        with tts.accelerate(model, directions, plan=plan, forecast=config.forecast):
            return [run(plan, b) for b in batches(val_idx, None)]

    meta = dict(training_metadata(args), n_train_samples=len(train_idx), n_val_samples=len(val_idx),
                data_seed=data_seed)
    return exit_when_stopped(lambda: fit(pruner, config, train_epoch=train_epoch, validate=validate, metadata=meta,
                                         steps=args.steps, memory_tokens=1))


if __name__ == "__main__":
    main()
