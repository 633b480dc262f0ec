#!/usr/bin/env bash
# The robot frontier: success (Push-T: mean best coverage) against policy-call latency for TASK=lift
# (default) or can (or a policy given by CKPT, with TRAJ its recorded trajectories; Push-T's:
# TASK=pusht CKPT=checkpoints/pusht_mh_dpt_17k TRAJ=data/trajectories/pusht-pusht_mh_dpt_17k_full.pt
# ALL_EPISODES=1), every method on the same test episodes (SEEDS,
# default 3 x 50) and timed against one dense reference in one process (eval/frontier_latency.py,
# batch 1 and 28). Methods: dense DDPM-100; DDIM-k (k = 2 3 4 5 7 10 16), trailing DDIM-k (2 3 5 7 10),
# DPM-Solver++-k (2 3 5 6 7 10 16 20: a step count near the latency of every sparse point), the
# policy's own stochastic DDPM on k steps (3 5 7 10 16 20: it keeps DDPM's fresh noise per step); searched whole steps at 90-98% on DDPM-100; the TTS step pruner served at
# those budgets; TTS on DDIM-20 and DDIM-10 bases at 7 computed steps (uniform and searched); the
# BAC-style schedule, uniform and FORA-interval timestep reuse at 93%. Resumable; a full run is
# several hours on 2 CPU cores (PARTS=success,latency,figures picks stages; ALL_EPISODES=1 uses
# every recorded episode, for a policy that rarely succeeds). Then python eval/tables.py
# METHODS="dense ddim:3 ... file:SCHEDULE.json" runs only those methods and searches nothing; with
# TRAJ_EPISODES=16 the recorded trajectories are that few (enough for timing, not for a search), e.g.
# the dropout-0.3 Lift policy's frontier (about 40 min):
#   TASK=lift CKPT=checkpoints/lift_mh_dpt_dropout0.3 TRAJ=data/trajectories/lift-lift_mh_dpt_dropout0.3_timing.pt \
#   TRAJ_EPISODES=16 METHODS="dense ddim:3 ddim:7 ddim:3:trailing dpm:3 dpm:7 dpm:10 dpm:20 ddpm:3 ddpm:7 ddpm:10
#   ddpm:20 file:results/schedules/lift-lift_mh_dpt_dropout0.3_steps_0.93.json
#   file:results/schedules/lift-lift_mh_dpt_dropout0.3_steps_0.93_rollout_early.json uniform:0.93:timestep" \
#   bash recipes/frontier.sh
set -euo pipefail
source "$(dirname "$0")/lib.sh"
ckpt=${CKPT:-}
traj=${TRAJ:-}
robot_task "${TASK:-lift}"
CKPT=${ckpt:-$CKPT}
TRAJ=${traj:-$TRAJ}
bundled=$([ "$CKPT" = "checkpoints/${TASK}_dpt" ] && echo 1 || echo "")
policy=$TASK
[ -n "$bundled" ] || policy=${TASK}-$(basename "$CKPT")
sched=results/schedules/${policy}  # schedules and pruners belong to one policy
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes "${TRAJ_EPISODES:-112}" \
    --out "$TRAJ" --resume --threads "${THREADS:-2}"  # the schedule search calibrates on them
have() {  # a file: method runs only where its schedule was made
  local m=${1#file:}
  [[ $1 != file:* ]] || [ -f "${m%%+*}" ]
}
if [ -n "${METHODS:-}" ]; then
  methods=(dense)
  for m in $METHODS; do [ "$m" = dense ] || methods+=("$m"); done
else
methods=(dense)
for k in 2 3 4 5 7 10 16; do methods+=("ddim:$k"); done
for k in 2 3 5 7 10; do methods+=("ddim:$k:trailing"); done
for k in 2 3 5 6 7 10 16 20; do methods+=("dpm:$k"); done
for k in 3 5 7 10 16 20; do methods+=("ddpm:$k"); done
for rho in 0.9 0.93 0.95 0.97 0.98; do
  search_steps "${sched}_steps_${rho}.json" "$rho"
  methods+=("file:${sched}_steps_${rho}.json")
  if [ -n "$bundled" ] && [ -f "checkpoints/pruners/$TTS_PRUNER.json" ]; then
    methods+=("pruner:checkpoints/pruners/$TTS_PRUNER@${rho}")
  fi
done
# the searched steps the task's TTS row starts from, where they are not the 64-call ones (Can: 256 calls)
methods+=("file:${sched}_steps_0.93_256calls.json")
search_steps "${sched}_steps_ddim20_0.65.json" 0.65 --sampler ddim:20
search_steps "${sched}_steps_ddim10_0.3.json" 0.3 --sampler ddim:10
methods+=("uniform:0.65:timestep+ddim:20" "file:${sched}_steps_ddim20_0.65.json+ddim:20"
          "uniform:0.3:timestep+ddim:10" "file:${sched}_steps_ddim10_0.3.json+ddim:10"
          "file:${sched}_bac_0.93.json" "uniform:0.93:timestep" "every_n:14:timestep")
fi
parts=${PARTS:-success,latency,figures}
if [[ $parts == *success* ]]; then
  for m in "${methods[@]}"; do
    have "$m" || continue
    evaluate --method "$m"
  done
fi
if [[ $parts == *latency* ]]; then
  # shellcheck disable=SC2046
  python eval/frontier_latency.py --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" --batch 1 28 \
      --trials "${TRIALS:-3}" --threads "${THREADS:-2}" --resume $(all_episodes) \
      --methods $(for m in "${methods[@]:1}"; do have "$m" && echo "$m"; done)
fi
if [[ $parts == *figures* ]]; then
  python eval/figures.py frontier --task "$TASK" --checkpoint "$CKPT"
fi
python eval/tables.py
