"""Train a TTS pruner on dense-policy trajectories (:func:`tts.policy_training.train_policy_pruner`),
on the CPU or a GPU (``--device cuda``).

    python eval/train_pruner.py --trajectories data/trajectories/lift.pt --checkpoint checkpoints/lift_dpt \
        --out checkpoints/lift_pruner --sparsity 0.93 --n-train 32 --n-val 16 --epochs 6

Episode groups of ``--batch`` run in lockstep, one optimizer step per policy call (frame): frame 0
is the dense call that fills the rollout cache and is excluded from the loss; every later frame runs
the full K-step sampler with straight-through gates and minimises L1(sparse action_pred, dense
action_pred) + lambda * |reuse fraction - sparsity| per sample. ``--paired`` replays each frame's
recorded noise seed; the default, like the paper, uses fresh noise. Validation uses test-time argmax
decisions (``--val-mode``). The best epoch (validation L1 + lambda * |sparsity error|) is written as
``<out>.safetensors/.json``; state is saved after every group of episodes under ``runs/<out name>/``
(``--run-dir``) and ``--resume`` continues from it. Creating the file ``STOP`` in that directory stops
the run at its next save (exit status 3), with nothing lost. Every option is the field of the same name of
:class:`tts.policy_training.PolicyPrunerTrainingConfig`.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import add_all_episodes_option, add_device_option, parse_args, torch_device  # noqa: E402
from common.training_args import add_training_args, exit_when_stopped, training_metadata  # noqa: E402

from tts.adapters.dp_policy import load_policy  # noqa: E402
from tts.policy_training import PolicyPrunerTrainingConfig, build_policy_pruner, train_policy_pruner  # noqa: E402
from tts.trajectories import load_trajectories  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectories", type=Path, required=True)
    ap.add_argument("--checkpoint", type=Path, required=True, help="the (frozen) policy")
    add_training_args(ap, sparsity=0.93, directions="forward,timestep,rollout", batch=16)
    ap.add_argument("--n-train", type=int, default=32)
    ap.add_argument("--n-val", type=int, default=16)
    ap.add_argument("--paired", action="store_true", help="replay the dense call's noise (paired target)")
    ap.add_argument("--loss-space", choices=["raw", "normalized"], default="raw",
                    help="L1 on raw actions (the paper) or on the policy's normalised actions")
    ap.add_argument("--static", action="store_true",
                    help="train a static router instead (Learning-to-Cache-style baseline: one decision per "
                         "step x branch, not per observation)")
    ap.add_argument("--head-bias", default=None,
                    help="initial head bias per option, compute first, e.g. 2,0,1,0 for (C, F, T, R): when the "
                         "sparsity term pushes compute down, the preferred direction takes over first")
    ap.add_argument("--init-schedule", type=Path, default=None,
                    help="warm start: fit the pruner to a searched static schedule (eval/search_static.py JSON) "
                         "by cross-entropy before the straight-through training")
    ap.add_argument("--recipe", choices=["ours", "reference"], default="ours",
                    help="reference: the reference implementation's recipe as defaults (pruner hidden 512, 8 heads, "
                         "FF 1024, head bias zero, AdamW lr 1e-4, weight decay 1e-4, warm-up then linear decay, no "
                         "clipping, batches of 16 episodes, 20 epochs, unpaired noise); options given explicitly win")
    first, _ = ap.parse_known_args(argv)
    if first.recipe == "reference":
        recipe = PolicyPrunerTrainingConfig.reference(out=first.out, directions=first.directions)
        ap.set_defaults(**{k: getattr(recipe, k) for k in ("hidden", "heads", "ffn", "lr", "weight_decay",
                                                           "lr_schedule", "clip_grad", "batch", "epochs")},
                        head_bias=",".join(str(b) for b in recipe.head_bias))
    add_all_episodes_option(ap)
    add_device_option(ap)
    args = parse_args(ap, argv)
    device = torch_device(args.device)
    try:
        config = PolicyPrunerTrainingConfig.from_dict(vars(args))
    except ValueError as e:
        ap.error(str(e))
    torch.manual_seed(args.seed)  # before the policy is built: the pruner's initial weights follow it
    episodes, traj_meta = load_trajectories(args.trajectories, successful_only=not args.all_episodes)
    policy = load_policy(args.checkpoint).to(device)
    meta = training_metadata(args)
    meta.update(policy=str(args.checkpoint), trajectory_collection=traj_meta.get("command"))
    pruner = build_policy_pruner(policy, config).to(device)
    exit_when_stopped(lambda: train_policy_pruner(policy, episodes, config, pruner=pruner, metadata=meta))


if __name__ == "__main__":
    main()
