#!/usr/bin/env bash
# The main rows of the robot table (issue 4) for TASK=lift (default) or can, from the bundled policy
# checkpoint (checkpoints/<task>_dpt): dense-policy trajectories (collected if missing), dense
# DDPM-100, DDIM-7 (matched FLOPs), the BAC-style per-branch schedule and the whole-step schedule
# searched offline, the TTS step-query pruner started from the searched steps (exact budget, 93%),
# its decisions vs its prior, the per-call oracle headroom around the searched steps, latency at
# batch 1 and 28 against dense in one process, the figures (docs/<task>_*.png), for Can the same
# from whole steps searched on 256 calibration calls (robot_baselines.sh parts c256 c256tts c256ts),
# then the tables. Every step is resumable and skipped when its output exists.
# SEEDS: 6 test seeds for Can, 3 for Lift (x 50 episodes). ~1.5 h for Can on 2 CPU cores from scratch.
# The other rows: scripts/robot_baselines.sh, budget_transfer.sh, data_efficiency.sh.
set -euo pipefail
source "$(dirname "$0")/env.sh"
robot_task "${TASK:-lift}"
[ "$TASK" = can ] && export SEEDS=${SEEDS:-100000 100050 100100 100150 100200 100250}
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 112 --out "$TRAJ"
evaluate --method dense
evaluate --method ddim --steps 7
[ -f "results/schedules/${TASK}_bac_0.93.json" ] || python eval/search_static.py --checkpoint "$CKPT" \
    --trajectories "$TRAJ" --sparsity 0.93 0.95 0.9 --threads 2 --out "results/schedules/${TASK}_bac.json"
evaluate --method static --plan "file:results/schedules/${TASK}_bac_0.93.json"
steps=results/schedules/${TASK}_steps_0.93.json
search_steps "$steps" 0.93
evaluate --method static --plan "file:$steps"
latency() {  # latency OUT_NAME ARGS...: eval/latency.py at batch 1 and 28 unless its result exists
  local out=results/robot/latency_${TASK}_$1.json; shift
  [ -f "$out" ] || python eval/latency.py --threads 2 --batch 1 28 --task "$TASK" --checkpoint "$CKPT" \
      --trajectories "$TRAJ" "$@"
}
checks() {  # checks PRUNER_NAME: a table TTS pruner's held-out decisions vs its prior, and its latency
  local pruner=checkpoints/pruners/$1
  [ -f "results/robot/agreement_${TASK}_$1.json" ] || python eval/pruner_agreement.py --task "$TASK" \
      --checkpoint "$CKPT" --trajectories "$TRAJ" --pruner "$pruner" --sparsity 0.93
  latency "tts-$1-budget0.93" --method tts --pruner "$pruner" --sparsity 0.93
}
pruner=checkpoints/pruners/${TASK}_tts_steps1q_0.93
step_pruner "${pruner##*/}" "$steps" 0.93 --directions timestep,rollout
checks "${pruner##*/}"
headroom "$steps"
latency "static-${TASK}_steps_0.93" --method static --plan "file:$steps"
[ -f "docs/${TASK}_pruning_masks.png" ] || python eval/figures.py masks --task "$TASK" --checkpoint "$CKPT" \
    --trajectories "$TRAJ" --pruner "$pruner" --sparsity 0.93
[ -f "docs/${TASK}_feature_similarity.png" ] || python eval/figures.py similarity --task "$TASK" \
    --checkpoint "$CKPT" --trajectories "$TRAJ"
if [ "$TASK" = can ]; then  # Can's TTS row within 2 points: the steps searched on 256 calls, then the pruner
  PARTS="c256 c256tts c256ts" bash scripts/robot_baselines.sh
  checks "${TASK}_tts_steps1q_c256_0.93"
fi
python eval/tables.py
