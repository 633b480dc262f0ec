#!/usr/bin/env bash
# Success vs calibration data (the paper's Figs 10-11 shape) for the searched whole-step schedule: the
# compute steps are searched (eval/search_static.py --objective output) on the first N recorded training
# trajectories, N = 1 2 4 8 16 (32 is results/schedules/<task>_steps_0.93.json), then evaluated on 3 test
# seeds x 50 episodes. WITH_PRUNER=1 (what pruner_data_efficiency.sh sets) then trains the step-query TTS
# pruner from each schedule on the same N trajectories (validation: the next 2) and evaluates it the same
# way. Resumable: every schedule / pruner / result that exists is skipped (FORCE=1 redoes the searches and
# static evaluations). Needs data/trajectories/<task>.pt (eval/collect_trajectories.py). About 25 min for
# Lift, 36 min for Can on 2 CPU cores (+ about 8 min per N with the pruner).
# Then: python eval/figures.py data-efficiency --task <task>
set -euo pipefail
source "$(dirname "$0")/lib.sh"
robot_task "${TASK:-lift}"
RHO=0.93
for n in ${NS:-1 2 4 8 16}; do
  sched=results/schedules/${TASK}_steps_${RHO}_${n}traj.json
  if [ -n "${FORCE:-}" ]; then
    rm -f "$sched" results/robot/${TASK}_file-${TASK}_steps_${RHO}_${n}traj_*.json
  fi
  search_steps "$sched" "$RHO" --episodes "$n"
  evaluate --method "file:$sched"
  [ -n "${WITH_PRUNER:-}" ] || continue
  NTRAIN=$n NVAL=2 EPOCHS=3 step_pruner "${TASK}_tts_${RHO}_${n}traj" "$sched" "$RHO" \
      --directions timestep,rollout --batch "$(( n < 16 ? n : 16 ))"
done
