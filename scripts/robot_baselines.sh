#!/usr/bin/env bash
# Matched-FLOPs rows of the robot table (issue 4), 3 test seeds x 50 episodes each, at 93% reuse
# unless said otherwise:
#   - single-direction static schedules: FORA-style interval (timestep), rollout, forward (uniform:)
#   - single-direction TTS pruners: the step-query recipe of the table's TTS row (searched compute
#     steps as prior, tied branches, exact-budget gates, paired) with timestep-only, rollout-only or
#     forward-only reuse (--prior-reuse maps the prior's reuse decisions to that direction)
#   - Learning-to-Cache-style learned static router (one logit per step x branch, timestep reuse,
#     exact-budget gates), served at exactly 93%
#   - TTS at 95%: searched steps at 0.95 + the step-query pruner trained there
#   - bste: the TTS row's step-query pruner retrained with exact-budget straight-through gates (before
#     commit 65c354a eval/train_pruner.py ignored --train-budget: argmax gates in training)
#   - fewer sampling steps: DDIM-10 and DDIM-16 (DDIM-7, the matched-FLOPs one: scripts/robot_table.sh)
#   - c256: the searched whole steps with 256 calibration calls instead of 64 (held-out error + success);
#     c256tts: the TTS row's pruner trained from that prior; c256ts: the same, timestep only (on Can
#     scripts/robot_table.sh runs these three with its 6 test seeds)
# Resumable: finished searches, pruners and evaluations are skipped. TASK=lift (default) or can;
# EPOCHS defaults to 3 (lift) / 1 (can), as for the table's TTS rows; PARTS picks and orders the parts
# (default: statics timestep rollout forward bste l2c rho95 ddim c256 c256tts c256ts); SEEDS as in
# env.sh. Then: python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/env.sh"
robot_task "${TASK:-lift}"
searched() { echo "results/schedules/${TASK}_steps_$1.json"; }  # the searched steps at sparsity $1

part_statics() {
  for d in timestep rollout forward; do
    evaluate --method static --plan "uniform:0.93:$d"
  done
}
part_timestep() { step_pruner "${TASK}_tts_steps1q_timestep_0.93" "$(searched 0.93)" 0.93 --directions timestep; }
part_rollout() {
  step_pruner "${TASK}_tts_steps1q_rollout_0.93" "$(searched 0.93)" 0.93 --directions rollout --prior-reuse rollout
}
part_forward() {  # reuse of the last computed branch of the same kind (in this step or an earlier one)
  step_pruner "${TASK}_tts_steps1q_forward_0.93" "$(searched 0.93)" 0.93 --directions forward --prior-reuse forward
}
part_bste() {  # the TTS row's recipe retrained since the fix that makes --train-budget effective
  step_pruner "${TASK}_tts_steps1q_bste_0.93" "$(searched 0.93)" 0.93 --directions timestep,rollout
}
part_l2c() {
  train_named "${TASK}_l2c_budget_0.93" --static --directions timestep --sparsity 0.93 --train-budget --lr 1e-2 \
      --val-mode budget
  evaluate --method tts --pruner "checkpoints/pruners/${TASK}_l2c_budget_0.93" --sparsity 0.93
}
part_rho95() {
  search_steps "$(searched 0.95)" 0.95
  step_pruner "${TASK}_tts_steps1q_0.95" "$(searched 0.95)" 0.95 --directions timestep,rollout
}
part_c256() {  # the whole-step search on 256 calibration calls instead of 64, held-out error, success
  local sched
  sched=$(searched 0.93_c256)
  CALLS=256 search_steps "$sched" 0.93
  headroom "$sched"
  evaluate --method static --plan "file:$sched"
}
# the TTS row's recipe from the 256-call searched steps: timestep + rollout, and timestep only
part_c256tts() { step_pruner "${TASK}_tts_steps1q_c256_0.93" "$(searched 0.93_c256)" 0.93 --directions timestep,rollout; }
part_c256ts() { step_pruner "${TASK}_tts_steps1q_c256_timestep_0.93" "$(searched 0.93_c256)" 0.93 --directions timestep; }
part_ddim() {
  for steps in 10 16; do
    evaluate --method ddim --steps "$steps"
  done
}

for part in ${PARTS:-statics timestep rollout forward bste l2c rho95 ddim c256 c256tts c256ts}; do
  "part_$part"
done
