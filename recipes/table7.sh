#!/usr/bin/env bash
# The paper's Table 7 shape at 93% on one policy (TASK, CKPT; default the MH-style Lift policy):
# dense; the few-step samplers at the same latency; the searched static whole steps; TTS pruners with
# the reference recipe (eval/train_pruner.py --recipe reference: hidden 512, 8 heads, FF 1024, head bias
# zero, AdamW 1e-4, 20 epochs, batches of 16 full-horizon episodes, unpaired noise), trained from scratch
# for each direction set (forward / timestep / rollout / all three) and, for all three, from the
# searched prior; their agreement with the prior on held-out episodes, the oracle headroom around the
# searched steps, and the mask and feature-similarity figures. Every step is resumable and skipped
# when its output exists. A reference-length pruner training is hours on 2 CPU cores (the device
# machine of a session, when lent, is the place for it). Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
ckpt=${CKPT:-checkpoints/lift_mh_dpt}
robot_task "${TASK:-lift}"
CKPT=$ckpt
policy=${TASK}-$(basename "$CKPT")
TRAJ=data/trajectories/${policy}_full.pt
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 112 \
    --full-horizon --out "$TRAJ" --resume
steps=results/schedules/${policy}_steps_0.93.json
search_steps "$steps" 0.93
reference_pruner() {  # NAME DIRECTIONS [ARGS...]: the reference recipe on 96 train / 16 validation episodes
  local name=$1 dirs=$2; shift 2
  [ -f "checkpoints/pruners/$name.json" ] || python eval/train_pruner.py --recipe reference --trajectories "$TRAJ" \
      --checkpoint "$CKPT" --out "checkpoints/pruners/$name" --directions "$dirs" --sparsity 0.93 \
      --n-train 96 --n-val 16 --threads 2 --run-dir "runs/$name" --resume "$@"
}
evaluate --method dense
for m in ddim:7 ddim:3 ddim:3:trailing dpm:3 "file:$steps"; do evaluate --method "$m"; done
for dirs in forward timestep rollout forward,timestep,rollout; do
  name=${policy}_reference_${dirs//,/-}_0.93
  reference_pruner "$name" "$dirs"
  evaluate --method "pruner:checkpoints/pruners/$name"
done
name=${policy}_reference_prior_0.93
reference_pruner "$name" forward,timestep,rollout --prior "$steps"
evaluate --method "pruner:checkpoints/pruners/$name"
[ -f "results/robot/agreement_${TASK}_$name.json" ] || python eval/pruner_agreement.py --task "$TASK" \
    --checkpoint "$CKPT" --trajectories "$TRAJ" --pruner "checkpoints/pruners/$name"
headroom "$steps"
[ -f "docs/${policy}_pruning_masks.png" ] || python eval/figures.py masks --task "$TASK" --checkpoint "$CKPT" \
    --trajectories "$TRAJ" --pruner "checkpoints/pruners/${policy}_reference_forward-timestep-rollout_0.93"
[ -f "docs/${policy}_feature_similarity.png" ] || python eval/figures.py similarity --task "$TASK" \
    --checkpoint "$CKPT" --trajectories "$TRAJ"
python eval/tables.py
