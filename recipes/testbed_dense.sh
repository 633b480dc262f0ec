#!/usr/bin/env bash
# Dense DDPM-100 success of every testbed policy on the 3 test seeds x 50 episodes (the rows the
# testbed reports next to its validation runs): the MH-style Lift, Can and Square policies and the
# Square policy trained on the expert's noisy demonstrations. Skips policies whose checkpoint is
# missing (make them with eval/train_policy.py, see docs/results/testbed.md) and finished runs.
#   bash recipes/testbed_dense.sh      # about 5-10 min per policy and seed on 2 CPU cores
# THREADS: torch threads (default 1). Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
for pair in lift:lift_mh_dpt can:can_mh_dpt square:square_dpt square:square_mh_dpt; do
  TASK=${pair%%:*}
  CKPT=checkpoints/${pair#*:}
  [ -f "$CKPT.json" ] || { echo "[skip] $CKPT: no checkpoint"; continue; }
  evaluate --method dense --threads "${THREADS:-1}"
done
