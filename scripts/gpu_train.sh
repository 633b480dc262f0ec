#!/usr/bin/env bash
# A stretch of a resumable training (eval/train_pruner.py or eval/train_policy.py) on a GPU machine
# that has PyTorch but no project install and no network (e.g. an offline cloud GPU), for BUDGET seconds
# (default 500):
#   BUDGET=500 OUT=FOLDER bash scripts/gpu_train.sh eval/train_pruner.py TRAINER_ARGS...
# The arguments are the trainer's, with --run-dir and --resume (as the recipes give them); --device
# cuda is added. The set-up is scripts/gpu_env.sh's.
# At the deadline the training is stopped with SIGTERM, then SIGKILL if it lingers (SIGINT would not do:
# a job started in the background of a script ignores it); its state holds the work up to its last
# save, written atomically. What comes back under OUT, with the log: the final checkpoint pair
# (<out>.safetensors / .json) if the trainer finished in this stretch, else its resumable state
# split into 15 MB parts (for machines that bring back files of a limited size; reassemble with
# `cat OUT/NAME.pt.part* > RUN_DIR/NAME.pt`) and the checkpoint JSON if there is one.
set -uo pipefail
t0=$(date +%s)
OUT=${OUT:-build/gpu/out}
mkdir -p "$OUT"
trainer=${1:?give the trainer script (eval/train_pruner.py or eval/train_policy.py)}
shift
# shellcheck disable=SC1091
source "$(dirname "$0")/gpu_env.sh" || exit 3
run_dir= out=
args=("$@")
for ((i = 0; i < ${#args[@]} - 1; i++)); do
  case ${args[i]} in --run-dir) run_dir=${args[i+1]} ;; --out) out=${args[i+1]} ;; esac
done
[ -n "$run_dir" ] || { echo "give --run-dir (the resumable state to bring back)" >&2; exit 2; }
left=$(( ${BUDGET:-500} - ($(date +%s) - t0) ))
echo "training for $left s"
timeout -k 30 "$left" python3 "$trainer" "$@" --device cuda 2>&1 | tr '\r' '\n' > "$OUT/train.log"
status=${PIPESTATUS[0]}
tail -n 20 "$OUT/train.log"
if [ "$status" -eq 0 ] && [ -n "$out" ]; then  # finished: the checkpoint is all that is needed
  cp "$out.safetensors" "$out.json" "$OUT/"
else
  for f in "$run_dir"/*.pt; do [ -f "$f" ] && split -b 15M -d "$f" "$OUT/$(basename "$f").part"; done
  [ -z "$out" ] || cp "$out.json" "$OUT/" 2>/dev/null
fi
ls -la "$OUT"
