#!/usr/bin/env bash
# The TTS pipeline on N recorded trajectories (issue 4, paper Figs 10-11 shape): the compute steps are
# searched on the first N trajectories (scripts/data_efficiency.sh writes results/schedules/<task>_steps_0.93_nN.json)
# and the step-query pruner is trained from them on the same N (validation: the next 2), then evaluated
# on 3 test seeds x 50 episodes. Resumable. Run scripts/data_efficiency.sh first (it makes the schedules).
# Then: python eval/figures.py data-efficiency --task <task>
set -euo pipefail
source "$(dirname "$0")/env.sh"
TASK=${TASK:-lift}
RHO=0.93
for n in ${NS:-1 2 4 8 16}; do
  sched=results/schedules/${TASK}_steps_${RHO}_n${n}.json
  [ -f "$sched" ] || { echo "missing $sched: run NS=$n bash scripts/data_efficiency.sh first" >&2; exit 1; }
  pruner=checkpoints/pruners/${TASK}_tts_steps1q_${RHO}_n${n}
  [ -f "$pruner.json" ] || python eval/train_pruner.py --trajectories data/trajectories/${TASK}.pt \
      --checkpoint checkpoints/${TASK}_dpt --out "$pruner" --sparsity $RHO --directions timestep,rollout \
      --prior "$sched" --tie-branches --step-query --train-budget --prior-margin 1.0 --lr 2e-3 --val-mode budget \
      --n-train "$n" --n-val 2 --epochs 3 --batch "$(( n < 16 ? n : 16 ))" --paired --threads 2 \
      --run-dir "runs/${TASK}_tts_steps1q_${RHO}_n${n}" --resume
  eval_seeds --task "$TASK" --checkpoint checkpoints/${TASK}_dpt --method tts --pruner "$pruner" --sparsity $RHO
done
