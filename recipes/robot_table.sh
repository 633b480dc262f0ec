#!/usr/bin/env bash
# The main rows of the robot table for TASK=lift (default) or can, from the bundled policy checkpoint
# (checkpoints/<task>_dpt): dense-policy trajectories (collected if missing), dense DDPM-100, DDIM-7
# (matched MACs), the BAC-style per-branch schedule and the whole-step schedule searched offline, the
# TTS step-query pruner started from the searched steps (exact budget, 93%; for Can the steps searched
# on 256 calibration calls and the pruners from them: robot_baselines.sh parts c256 c256tts c256ts),
# its decisions vs its prior, the per-call oracle headroom around the searched steps, latency at batch
# 1 and 28 against dense in one process, the figures (docs/<task>_*.png); then the tables. Every step
# is resumable and skipped when its output exists.
# SEEDS: 6 test seeds for Can, 3 for Lift (x 50 episodes). About 1 h for Lift and 1.5 h for Can on
# 2 CPU cores from scratch.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
robot_task "${TASK:-lift}"
[ "$TASK" = can ] && export SEEDS=${SEEDS:-100000 100050 100100 100150 100200 100250}
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 112 --out "$TRAJ"
evaluate --method dense
evaluate --method ddim:7
[ -f "results/schedules/${TASK}_bac_0.93.json" ] || python eval/search_static.py --checkpoint "$CKPT" \
    --trajectories "$TRAJ" --sparsity 0.93 0.95 0.9 --threads 2 --out "results/schedules/${TASK}_bac.json"
evaluate --method "file:results/schedules/${TASK}_bac_0.93.json"
steps=results/schedules/${TASK}_steps_0.93.json
search_steps "$steps" 0.93
evaluate --method "file:$steps"
checks() {  # checks PRUNER_NAME: a table TTS pruner's held-out decisions vs its prior, and its latency
  local pruner=checkpoints/pruners/$1
  [ -f "results/robot/agreement_${TASK}_$1.json" ] || python eval/pruner_agreement.py --task "$TASK" \
      --checkpoint "$CKPT" --trajectories "$TRAJ" --pruner "$pruner" --sparsity 0.93
  latency "pruner:$pruner@0.93"
}
if [ "$TASK" = can ]; then  # Can's TTS row: the steps searched on 256 calls, then the pruner from them
  PARTS="c256 c256tts c256ts" bash "$(dirname "$0")/robot_baselines.sh"
else
  step_pruner "$TTS_PRUNER" "$steps" 0.93 --directions timestep,rollout
fi
checks "$TTS_PRUNER"
headroom "$steps"
latency "file:$steps"
latency ddim:7
[ -f "docs/${TASK}_pruning_masks.png" ] || python eval/figures.py masks --task "$TASK" --checkpoint "$CKPT" \
    --trajectories "$TRAJ" --pruner "checkpoints/pruners/$TTS_PRUNER" --sparsity 0.93
[ -f "docs/${TASK}_feature_similarity.png" ] || python eval/figures.py similarity --task "$TASK" \
    --checkpoint "$CKPT" --trajectories "$TRAJ"
python eval/tables.py
