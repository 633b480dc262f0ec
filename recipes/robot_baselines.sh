#!/usr/bin/env bash
# Matched-MACs rows of the robot table, 3 test seeds x 50 episodes each, at 93% reuse unless said otherwise:
#   statics   single-direction static schedules: uniform:0.93:timestep (FORA-style), rollout, forward
#   timestep / rollout / forward
#             single-direction TTS pruners: the step-query recipe of the table's TTS row (searched compute
#             steps as prior, tied branches, exact-budget gates, paired) with timestep-only, rollout-only
#             or forward-only reuse (--prior-reuse maps the prior's reuse decisions to that direction)
#   budgetgates  the TTS row's step-query pruner trained with exact-budget straight-through gates
#   l2c       Learning-to-Cache-style learned static router (one logit per step x branch, timestep reuse,
#             exact-budget gates), served at exactly 93%
#   rho95     TTS at 95%: searched steps at 0.95 + the step-query pruner trained there
#   ddim      fewer sampling steps: DDIM-10 and DDIM-16 (DDIM-7, the matched-MACs one: robot_table.sh)
#   c256      the searched whole steps with 256 calibration calls instead of 64 (held-out error, success)
#   c256tts   the TTS row's pruner trained from that prior; c256ts: the same, timestep only
#             (on Can, robot_table.sh runs these three with its 6 test seeds)
# Resumable: finished searches, pruners and evaluations are skipped. TASK=lift (default) or can;
# EPOCHS defaults to 3 (lift) / 1 (can), as for the table's TTS rows; PARTS picks and orders the parts
# (default: all, in the order above); SEEDS as in lib.sh. About 2-3 h per task on 2 CPU cores.
# Then: python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
robot_task "${TASK:-lift}"
searched() { echo "results/schedules/${TASK}_steps_$1.json"; }  # the searched steps at sparsity $1

part_statics() {
  for d in timestep rollout forward; do
    evaluate --method "uniform:0.93:$d"
  done
}
part_timestep() { step_pruner "${TASK}_tts_timestep_0.93" "$(searched 0.93)" 0.93 --directions timestep; }
part_rollout() {
  step_pruner "${TASK}_tts_rollout_0.93" "$(searched 0.93)" 0.93 --directions rollout --prior-reuse rollout
}
part_forward() {  # reuse of the last computed branch of the same kind (in this step or an earlier one)
  step_pruner "${TASK}_tts_forward_0.93" "$(searched 0.93)" 0.93 --directions forward --prior-reuse forward
}
part_budgetgates() {
  step_pruner "${TASK}_tts_budgetgates_0.93" "$(searched 0.93)" 0.93 --directions timestep,rollout
}
part_l2c() {
  train_named "${TASK}_l2c_0.93" --static --directions timestep --sparsity 0.93 --train-budget --lr 1e-2 \
      --val-mode budget
  evaluate --method "pruner:checkpoints/pruners/${TASK}_l2c_0.93@0.93"
}
part_rho95() {
  search_steps "$(searched 0.95)" 0.95
  step_pruner "${TASK}_tts_0.95" "$(searched 0.95)" 0.95 --directions timestep,rollout
}
part_c256() {  # the whole-step search on 256 calibration calls instead of 64, held-out error, success
  local sched
  sched=$(searched 0.93_256calls)
  CALLS=256 search_steps "$sched" 0.93
  headroom "$sched"
  evaluate --method "file:$sched"
}
# the TTS row's recipe from the 256-call searched steps: timestep + rollout, and timestep only
part_c256tts() { step_pruner "${TASK}_tts_0.93_256calls" "$(searched 0.93_256calls)" 0.93 --directions timestep,rollout; }
part_c256ts() {
  step_pruner "${TASK}_tts_timestep_0.93_256calls" "$(searched 0.93_256calls)" 0.93 --directions timestep
}
part_ddim() {
  for steps in 10 16; do
    evaluate --method "ddim:$steps"
  done
}

for part in ${PARTS:-statics timestep rollout forward budgetgates l2c rho95 ddim c256 c256tts c256ts}; do
  "part_$part"
done
