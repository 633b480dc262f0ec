#!/usr/bin/env bash
# One pruner for several target sparsities (issue 4): the step-level TTS pruner trained at 0.93, served
# in exact-budget mode at 0.90 and 0.95, against step-level pruners trained at 0.90 / 0.95 with the same
# recipe (searched compute steps as prior, tied branches, budget STE, 3 epochs, paired, 96 trajectories).
# 3 test seeds x 50 episodes each. Resumable: finished searches, pruners and evaluations are skipped.
# ~45 min for Lift on 2 CPU cores. Then: python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/env.sh"
robot_task "${TASK:-lift}"
for rho in ${RHOS:-0.9 0.95}; do  # trained at 0.93, served at rho
  evaluate --method tts --pruner "checkpoints/pruners/${TASK}_tts_steps_0.93" --sparsity "$rho"
done
for rho in ${RHOS:-0.9 0.95}; do  # trained and served at rho
  sched=results/schedules/${TASK}_steps_${rho}.json
  search_steps "$sched" "$rho"
  train_named "${TASK}_tts_steps_${rho}" --sparsity "$rho" --directions timestep,rollout --prior "$sched" \
      --tie-branches --train-budget --prior-margin 1.0 --lr 2e-3 --val-mode budget
  evaluate --method tts --pruner "checkpoints/pruners/${TASK}_tts_steps_${rho}" --sparsity "$rho"
done
