#!/usr/bin/env bash
# One pruner for several target sparsities (issue 4): the step-level TTS pruner trained at 0.93, served
# in exact-budget mode at 0.90 and 0.95, against step-level pruners trained at 0.90 / 0.95 with the same
# recipe (searched compute steps as prior, tied branches, budget STE, 3 epochs, paired, 96 trajectories).
# 3 test seeds x 50 episodes each. Resumable: finished searches, pruners and evaluations are skipped.
# ~45 min for Lift on 2 CPU cores. Then: python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/env.sh"
TASK=${TASK:-lift}
evaluate() {  # evaluate PRUNER RHO: 3 seeds, exact budget RHO
  eval_seeds --task "$TASK" --checkpoint checkpoints/${TASK}_dpt --method tts --pruner "$1" --sparsity "$2"
}
for rho in ${RHOS:-0.9 0.95}; do
  evaluate checkpoints/pruners/${TASK}_tts_steps_0.93 "$rho"  # trained at 0.93, served at rho
done
for rho in ${RHOS:-0.9 0.95}; do
  sched=results/schedules/${TASK}_steps_${rho}.json
  [ -f "$sched" ] || python eval/search_static.py --checkpoint checkpoints/${TASK}_dpt \
      --trajectories data/trajectories/${TASK}.pt --sparsity "$rho" --objective output --calls 64 --batch 64 \
      --shifts 1,2,4,8 --sweeps 40 --threads 2 --out "$sched"
  pruner=checkpoints/pruners/${TASK}_tts_steps_${rho}
  [ -f "$pruner.json" ] || python eval/train_pruner.py --trajectories data/trajectories/${TASK}.pt \
      --checkpoint checkpoints/${TASK}_dpt --out "$pruner" --sparsity "$rho" --directions timestep,rollout \
      --prior "$sched" --tie-branches --train-budget --prior-margin 1.0 --lr 2e-3 --val-mode budget \
      --n-train 96 --n-val 16 --epochs 3 --paired --threads 2 --run-dir "runs/${TASK}_tts_steps_${rho}" --resume
  evaluate "$pruner" "$rho"  # trained and served at rho
done
