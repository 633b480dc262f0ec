# Sourced by the robot recipes: the set-up of scripts/env.sh, then the helpers the recipes share.
# shellcheck disable=SC1091
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/env.sh"

# state_dir NAME: where a recipe's long training keeps its resumable state (optimizer, step, RNGs).
# It is tracked, not ignored: a new checkout of the repository has no ignored files, so the state of an
# interrupted training survives on another checkout only if it is committed. Commit it once, when you
# stop, not after every epoch: each committed version of a ~50 MB state adds its full size to what a
# push carries. Each recipe deletes it (finish_state) once its training has finished.
state_dir() { echo "checkpoints/in_progress/$1"; }

# finish_state NAME: drop NAME's resumable state once its training has written its final checkpoint.
finish_state() { rm -rf "$(state_dir "$1")"; }

# eval_seeds ROBOT_ARGS...: eval/robot.py on 50 test episodes for each of $SEEDS (default: the 3
# evaluation seeds); --resume skips finished runs and continues cut-off ones; THREADS sets torch threads.
eval_seeds() {
  local seed
  for seed in ${SEEDS:-100000 100050 100100}; do
    python eval/robot.py ${THREADS:+--threads "$THREADS"} "$@" --episodes 50 --seed "$seed" --resume
  done
}

# steps_recipe RHO SCHEDULE: eval/train_pruner.py flags of the table's step-level TTS pruner (searched
# compute steps as prior, one decoder query per step, exact-budget gates, validation at the budget).
steps_recipe() {
  echo --sparsity "$1" --prior "$2" --tie-branches --step-query --train-budget --prior-margin 1.0 --lr 2e-3 \
       --val-mode budget
}

# step_pruner NAME SCHEDULE RHO TRAIN_ARGS...: the table's step-level TTS pruner (steps_recipe) started
# from SCHEDULE, trained (train_named) and evaluated (evaluate) at sparsity RHO.
step_pruner() {
  local name=$1 sched=$2 rho=$3; shift 3
  # shellcheck disable=SC2046
  train_named "$name" $(steps_recipe "$rho" "$sched") "$@"
  evaluate --method "pruner:checkpoints/pruners/$name@$rho"
}

# robot_task TASK: the per-task paths and training sizes the robot recipes share (TASK, CKPT, TRAJ,
# NTRAIN: the table's pruners train on 96 Lift / 89 Can trajectories with the next 16 held out for
# validation, EPOCHS: 3 Lift / 1 Can unless set; TTS_PRUNER: the name of the task's TTS row, on Can
# the one from the steps searched on 256 calibration calls).
robot_task() {
  TASK=$1
  CKPT=checkpoints/${TASK}_dpt
  TRAJ=data/trajectories/${TASK}.pt
  TTS_PRUNER=${TASK}_tts_0.93$([ "$TASK" = can ] && echo _256calls || true)
  NTRAIN=$([ "$TASK" = can ] && echo 89 || echo 96)
  EPOCHS=${EPOCHS:-$([ "$TASK" = can ] && echo 1 || echo 3)}
}

# evaluate ROBOT_ARGS...: eval_seeds on the current robot_task's policy.
evaluate() { eval_seeds --task "$TASK" --checkpoint "$CKPT" "$@"; }

# all_episodes: --all-episodes when ALL_EPISODES=1, for the trajectory tools (search, pruner training,
# agreement, headroom, figures) of a policy that rarely succeeds (e.g. Push-T's): they then use every
# recorded episode instead of the successful ones.
all_episodes() { [ -z "${ALL_EPISODES:-}" ] || echo --all-episodes; }

# trained NAME: whether checkpoints/pruners/NAME holds a finished training (eval/train_pruner.py writes
# the best epoch so far after every epoch, so an interrupted run leaves a checkpoint that is not done).
trained() {
  [ -f "checkpoints/pruners/$1.json" ] && python -c 'import sys; from tts.training import training_finished
sys.exit(0 if training_finished(sys.argv[1]) else 1)' "checkpoints/pruners/$1.json"
}

# train_named NAME ARGS...: eval/train_pruner.py on the robot_task's trajectories (paired, resumable;
# skipped when its training finished: trained); NTRAIN / NVAL (default 16) / EPOCHS set the sizes.
train_named() {
  local name=$1; shift
  trained "$name" || { python eval/train_pruner.py --trajectories "$TRAJ" --checkpoint "$CKPT" \
      --out "checkpoints/pruners/$name" --n-train "$NTRAIN" --n-val "${NVAL:-16}" --epochs "$EPOCHS" --paired --threads "${THREADS:-2}" \
      --run-dir "$(state_dir "$name")" --resume $(all_episodes) "$@" && finish_state "$name"; }
}

# search_steps OUT RHO [SEARCH_ARGS...]: whole compute steps placed by output L1 (eval/search_static.py)
# at sparsity RHO on CALLS calibration calls (default 64), written to OUT unless it exists.
# ALL_EPISODES=1: calibrate on every recorded episode.
search_steps() {
  local out=$1 rho=$2; shift 2
  # shellcheck disable=SC2046
  set -- "$@" $(all_episodes)
  [ -f "$out" ] || python eval/search_static.py --checkpoint "$CKPT" --trajectories "$TRAJ" --sparsity "$rho" \
      --objective output --calls "${CALLS:-64}" --batch 64 --shifts 1,2,4,8 --sweeps 40 --threads "${THREADS:-2}" --out "$out" "$@"
}

# headroom SCHEDULE: eval/oracle_headroom.py around a searched whole-step schedule, unless its result
# (results/robot/headroom_<task>_<schedule name>.json) exists.
headroom() {
  local name=${1##*/}
  [ -f "results/robot/headroom_${TASK}_${name%.json}.json" ] || python eval/oracle_headroom.py --task "$TASK" \
      --checkpoint "$CKPT" --trajectories "$TRAJ" --schedule "$1" --threads "${THREADS:-2}" $(all_episodes)
}

# latency METHOD: eval/latency.py at batch 1 and 28 against dense in one process (skipped when done).
latency() {
  python eval/latency.py --threads 2 --batch 1 28 --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" \
      --method "$1" --resume $(all_episodes)
}
