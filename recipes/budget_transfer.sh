#!/usr/bin/env bash
# One pruner for several target sparsities: the branch-query TTS pruner trained at 0.93 (one decoder
# query per branch, decisions tied per step), served in exact-budget mode at 0.90 and 0.95, against the
# same recipe trained at 0.90 / 0.95 (searched compute steps as prior, tied branches, exact-budget gates,
# 3 epochs, paired, 96 trajectories). 3 test seeds x 50 episodes each. Resumable: finished searches,
# pruners and evaluations are skipped. About 45 min for Lift on 2 CPU cores. Then: python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
robot_task "${TASK:-lift}"
branchq() {  # branchq RHO: the branch-query pruner trained at RHO from the steps searched at RHO
  local sched=results/schedules/${TASK}_steps_$1.json
  search_steps "$sched" "$1"
  train_named "${TASK}_tts_branchq_$1" --sparsity "$1" --directions timestep,rollout --prior "$sched" \
      --tie-branches --train-budget --prior-margin 1.0 --lr 2e-3 --val-mode budget
}
branchq 0.93
for rho in ${RHOS:-0.9 0.95}; do  # trained at 0.93, served at rho
  evaluate --method "pruner:checkpoints/pruners/${TASK}_tts_branchq_0.93@$rho"
done
for rho in ${RHOS:-0.9 0.95}; do  # trained and served at rho
  branchq "$rho"
  evaluate --method "pruner:checkpoints/pruners/${TASK}_tts_branchq_$rho@$rho"
done
