#!/usr/bin/env bash
# Success vs calibration data (issue 4, paper Figs 10-11 shape) for the searched whole-step schedule:
# the compute steps are searched (eval/search_static.py --objective output) on the first N recorded
# training trajectories, N = 1 2 4 8 16 (32 is results/schedules/<task>_steps_0.93.json), then
# evaluated on 3 test seeds x 50 episodes. WITH_PRUNER=1 (what scripts/pruner_data_efficiency.sh sets)
# then trains the step-query TTS pruner from each schedule on the same N trajectories (validation:
# the next 2) and evaluates it the same way. Resumable: every schedule / pruner / result that exists
# is skipped (FORCE=1 redoes the static evaluations). Needs data/trajectories/<task>.pt
# (eval/collect_trajectories.py). ~25 min for Lift on 2 CPU cores (+ ~8 min per N with the pruner).
# Then: python eval/figures.py data-efficiency --task <task>
set -euo pipefail
source "$(dirname "$0")/env.sh"
TASK=${TASK:-lift}
RHO=0.93
for n in ${NS:-1 2 4 8 16}; do
  sched=results/schedules/${TASK}_steps_${RHO}_n${n}.json
  if [ ! -f "$sched" ] || [ -n "${FORCE:-}" ]; then
    python eval/search_static.py --checkpoint checkpoints/${TASK}_dpt --trajectories data/trajectories/${TASK}.pt \
        --sparsity $RHO --objective output --episodes "$n" --calls 64 --batch 64 --shifts 1,2,4,8 --sweeps 40 \
        --threads 2 --out "$sched"
  fi
  [ -n "${FORCE:-}" ] && rm -f results/robot/${TASK}_static-${TASK}_steps_${RHO}_n${n}_*.json
  eval_seeds --task "$TASK" --checkpoint checkpoints/${TASK}_dpt --method static --plan "file:$sched"
  [ -n "${WITH_PRUNER:-}" ] || continue
  pruner=checkpoints/pruners/${TASK}_tts_steps1q_${RHO}_n${n}
  # shellcheck disable=SC2046
  [ -f "$pruner.json" ] || python eval/train_pruner.py --trajectories data/trajectories/${TASK}.pt \
      --checkpoint checkpoints/${TASK}_dpt --out "$pruner" $(steps_recipe "$RHO" "$sched") \
      --directions timestep,rollout --n-train "$n" --n-val 2 --epochs 3 --batch "$(( n < 16 ? n : 16 ))" \
      --paired --threads 2 --run-dir "runs/${TASK}_tts_steps1q_${RHO}_n${n}" --resume
  eval_seeds --task "$TASK" --checkpoint checkpoints/${TASK}_dpt --method tts --pruner "$pruner" --sparsity $RHO
done
