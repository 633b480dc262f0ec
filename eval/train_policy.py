"""Train a low-dim Diffusion Policy transformer (DP-T) on a robomimic-layout dataset, on the CPU or a
GPU (``--device cuda``).

    python eval/train_policy.py --data data/lift_expert.hdf5 --out checkpoints/lift_dpt \
        --steps 6000 --batch 128 --seed 0

Resumable: training state is saved every ``--save-every`` steps under ``--run-dir`` and
``--resume`` continues from it. ``--init CKPT`` warm-starts from a finished checkpoint's weights
(same data and architecture) with a fresh optimizer and learning-rate cycle. The final EMA weights are written atomically as
``<out>.safetensors`` + ``<out>.json`` (config, data, command, git SHA, seed, time).
Model size (documented choice): 8 decoder layers like the paper's DP-T (24 prunable branches per
step), width 128 instead of 256 so that a task trains in under ~30 min on 2 CPU cores and the
bundled checkpoint stays near 4 MB in fp16.

``--obs-type image`` trains the visuomotor policy (:class:`tts.adapters.dp_image_policy.DiffusionTransformerHybridImagePolicy`)
on an image dataset (eval/render_demos.py): the cameras of ``--cameras`` through a ResNet-18 trunk of
``--encoder-width`` (64 is torchvision's; random ``--crop`` crops in training), plus the
proprioception keys (``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``: no object
state, as in Diffusion Policy's image runs); encoder and transformer train together.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import add_device_option, parse_args, provenance, torch_device  # noqa: E402
from common.model_training import EMA, restore_training_state, save_training_state  # noqa: E402

from tts.adapters.dp_image_policy import CAMERAS, DiffusionTransformerHybridImagePolicy, ImageEncoderConfig  # noqa: E402
from tts.adapters.dp_policy import DiffusionTransformerLowdimPolicy, PolicyConfig, load_policy, save_policy  # noqa: E402
from robot_suite.robomimic import describe_demonstrators, read_demos, read_env_args  # noqa: E402
from robot_suite.tasks import OBS_KEYS, TASKS, task_of_env  # noqa: E402


PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


def window_indices(lengths: list[int], horizon: int, n_obs: int, n_act: int) -> np.ndarray:
    """Diffusion Policy's sequence sampling over demos of ``lengths`` laid end to end: every start
    index, edge-padded (To-1 before, Ta-1 after). Returns [windows, horizon] frame indices; the
    first ``n_obs`` are the window's observation frames."""
    out, offset = [], 0
    for T in lengths:
        for start in range(-(n_obs - 1), T - horizon + n_act):
            out.append(offset + np.clip(np.arange(start, start + horizon), 0, T - 1))
        offset += T
    return np.stack(out)


def windows(demos, horizon: int, n_obs: int, n_act: int, keys=OBS_KEYS) -> tuple[torch.Tensor, torch.Tensor]:
    """Observation [N, To, D] and action [N, H, Da] windows of :func:`window_indices`."""
    idx = window_indices([len(d) for d in demos], horizon, n_obs, n_act)
    obs = np.concatenate([np.concatenate([d.obs[k] for k in keys], axis=-1) for d in demos]).astype(np.float32)
    act = np.concatenate([d.actions for d in demos]).astype(np.float32)
    return torch.from_numpy(obs[idx[:, :n_obs]]), torch.from_numpy(act[idx])


class ImageWindows:
    """An image dataset's windows, gathered per batch (frames are stored once, not per window):
    ``batch(i)`` -> (obs dict of [B, To, ...] per camera and proprioception key, actions [B, H, Da])."""

    def __init__(self, demos, cameras, keys, horizon: int, n_obs: int, n_act: int):
        self.idx = window_indices([len(d) for d in demos], horizon, n_obs, n_act)
        self.n_obs = n_obs
        self.frames = {c: np.concatenate([d.obs[c] for d in demos]) for c in cameras}
        self.low = {k: np.concatenate([d.obs[k] for d in demos]).astype(np.float32) for k in keys}
        self.act = torch.from_numpy(np.concatenate([d.actions for d in demos]).astype(np.float32))

    def __len__(self) -> int:
        return len(self.idx)

    def low_dim(self) -> torch.Tensor:
        """Every frame's proprioception [frames, D] (for the normaliser)."""
        return torch.from_numpy(np.concatenate(list(self.low.values()), axis=-1))

    def batch(self, rows: torch.Tensor) -> tuple[dict, torch.Tensor]:
        idx = self.idx[rows.numpy()]
        obs_idx = idx[:, :self.n_obs]
        obs = {c: torch.from_numpy(f[obs_idx]) for c, f in self.frames.items()}
        obs.update({k: torch.from_numpy(v[obs_idx]) for k, v in self.low.items()})
        return obs, self.act[idx]


def init_from(policy: DiffusionTransformerLowdimPolicy, path: Path) -> None:
    """Copy a finished checkpoint's weights into ``policy`` (normalisers included); a different
    architecture or observation layout is an error, not a partial load. Dropout rates may differ (they
    are not part of the weights): e.g. continuing a policy with the reference's dropout 0.3."""
    src = load_policy(path)

    def architecture(cfg) -> dict:
        return {k: v for k, v in cfg.model.items() if not k.startswith("p_drop")}

    if architecture(src.cfg) != architecture(policy.cfg) or list(src.cfg.obs_dims) != list(policy.cfg.obs_dims):
        raise SystemExit(f"--init {path}: its model config {src.cfg.model} / obs dims {src.cfg.obs_dims} differ "
                         f"from this run's {policy.cfg.model} / {policy.cfg.obs_dims}")
    policy.load_state_dict(src.state_dict())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True, help="checkpoint path without suffix")
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--layers", type=int, default=8)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--dropout", type=float, default=0.1,
                    help="dropout on attention weights and every residual branch (Diffusion Policy's p_drop_attn; "
                         "the reference trains its policies with 0.3)")
    ap.add_argument("--max-demos", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run-dir", type=Path, default=None, help="resumable state (default: runs/<out name>)")
    ap.add_argument("--save-every", type=int, default=500)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--init", type=Path, default=None,
                    help="warm start: a finished checkpoint (path without suffix) of the same architecture; its "
                         "weights start both the model and its EMA, the optimizer and LR cycle start afresh")
    ap.add_argument("--export-only", action="store_true",
                    help="write the checkpoint from the latest saved state (EMA) without training further")
    ap.add_argument("--obs-type", choices=["low_dim", "image"], default="low_dim",
                    help="image: the visuomotor policy on an image dataset (eval/render_demos.py)")
    ap.add_argument("--cameras", nargs="+", default=list(CAMERAS), help="image: the camera keys")
    ap.add_argument("--encoder-width", type=int, default=16,
                    help="image: channels of the ResNet-18 trunk's first stage (64 = torchvision's)")
    ap.add_argument("--crop", type=int, default=None, help="image: crop size (default: image size - 8)")
    add_device_option(ap)
    args = parse_args(ap, argv)
    device = torch_device(args.device)
    if args.export_only:
        args.resume = True

    torch.manual_seed(args.seed)
    keys = TASKS[task_of_env(read_env_args(args.data)["env_name"])].obs_keys
    image_cfg = None
    if args.obs_type == "image":
        keys = PROPRIO_KEYS
        demos = read_demos(args.data, [*args.cameras, *keys], limit=args.max_demos)
        size = int(demos[0].obs[args.cameras[0]].shape[1])
        image_cfg = ImageEncoderConfig(cameras=args.cameras, image_size=size, crop_size=args.crop or size - 8,
                                       width=args.encoder_width)
    else:
        demos = read_demos(args.data, keys, limit=args.max_demos)
    obs_dims = [int(demos[0].obs[k].shape[-1]) for k in keys]
    action_dim = int(demos[0].actions.shape[-1])
    H, To, Ta = 10, 2, 8
    if image_cfg is None:
        obs_w, act_w = windows(demos, H, To, Ta, keys)
        n_windows, low_dim = len(obs_w), obs_w
    else:
        data = ImageWindows(demos, args.cameras, keys, H, To, Ta)
        n_windows, low_dim, act_w = len(data), data.low_dim(), data.act
    cond_dim = sum(obs_dims) + (image_cfg.features if image_cfg else 0)
    cfg = PolicyConfig(
        model=dict(input_dim=action_dim, output_dim=action_dim, horizon=H, n_obs_steps=To, cond_dim=cond_dim,
                   n_layer=args.layers, n_head=args.heads, n_emb=args.width, p_drop_emb=0.0, p_drop_attn=args.dropout,
                   causal_attn=True, time_as_cond=True, obs_as_cond=True, n_cond_layers=0),
        obs_keys=list(keys), obs_dims=obs_dims, action_dim=action_dim, horizon=H, n_obs_steps=To,
        n_action_steps=Ta, num_train_timesteps=100, num_inference_steps=100, scheduler="ddpm")
    policy = (DiffusionTransformerLowdimPolicy(cfg) if image_cfg is None
              else DiffusionTransformerHybridImagePolicy(cfg, image_cfg))
    policy.obs_normalizer.fit(low_dim)
    policy.action_normalizer.fit(act_w)
    if args.init is not None:
        init_from(policy, args.init)
    policy.to(device)
    ema = EMA(policy, lambda n: min(0.9999, max(0.0, 1 - (1 + n) ** -0.75)))  # Diffusion Policy's schedule
    trained = list(policy.model.parameters()) + (list(policy.obs_encoder.parameters()) if image_cfg else [])
    opt = torch.optim.AdamW(trained, lr=args.lr, betas=(0.9, 0.95), weight_decay=1e-3)
    warmup = max(1, min(500, args.steps // 10))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(s, args.steps) / args.steps)))
    run_dir = args.run_dir or Path("runs") / args.out.name
    state_path = run_dir / "state.pt"
    step, losses = 0, []
    if args.resume and state_path.exists():
        st = torch.load(state_path, map_location="cpu", weights_only=False)
        step, losses = restore_training_state(st, "policy", policy, ema, opt, sched)
        print(f"resumed at step {step}")
    gen = torch.Generator().manual_seed(args.seed + step)
    t0 = time.time()
    policy.train()
    if args.export_only and not state_path.exists():
        raise SystemExit(f"--export-only: no saved state at {state_path}")
    with tqdm(total=args.steps, initial=step, desc=f"train {args.out.name}", disable=args.export_only) as bar:
        while step < args.steps and not args.export_only:
            idx = torch.randint(0, n_windows, (args.batch,), generator=gen)
            obs, act = (obs_w[idx], act_w[idx]) if image_cfg is None else data.batch(idx)
            obs = obs.to(device) if torch.is_tensor(obs) else {k: v.to(device) for k, v in obs.items()}
            loss = policy.compute_loss(obs, act.to(device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(trained, 1.0)
            opt.step()
            sched.step()
            ema.update(policy)
            step += 1
            losses.append(float(loss.detach()))
            bar.update(1)
            if step % 50 == 0:
                bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}")
            if step % args.save_every == 0 or step == args.steps:
                save_training_state(state_path, "policy", policy, ema, opt, sched, step, losses)
    meta = provenance(seeds={"train": args.seed})
    meta.update(init=str(args.init) if args.init else None, data=str(args.data), demos=len(demos), windows=n_windows, steps=args.steps, steps_done=step,
                obs_type=args.obs_type,
                batch=args.batch,
                lr=args.lr, final_loss=float(np.mean(losses[-200:])), train_seconds_this_run=time.time() - t0,
                note=f"trained on demonstrations from {describe_demonstrators(args.data)}")
    save_policy(ema.model, args.out, metadata=meta)
    print(f"saved {args.out}.safetensors / .json (final loss {meta['final_loss']:.4f})")


if __name__ == "__main__":
    main()
