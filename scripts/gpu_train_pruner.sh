#!/usr/bin/env bash
# A stretch of a resumable pruner training on a GPU machine that has PyTorch but no project install
# and no network (e.g. a lent cloud GPU), for BUDGET seconds (default 500):
#   BUDGET=500 OUT=FOLDER bash scripts/gpu_train_pruner.sh EVAL_TRAIN_PRUNER_ARGS...
# The arguments are eval/train_pruner.py's, with --run-dir and --resume (as recipes/table7.sh gives
# them); --device cuda is added. The set-up is scripts/gpu_env.sh's.
# At the deadline the training is stopped with SIGTERM, then SIGKILL if it lingers (SIGINT would not do:
# a job started in the background of a script ignores it); its state holds every finished episode group,
# written atomically. The state is then split into 15 MB parts under OUT (with the log and the
# checkpoint JSON) for machines that bring back files of a limited size. Reassemble with:
#   cat OUT/state.part* > RUN_DIR/pruner_state.pt
set -uo pipefail
t0=$(date +%s)
OUT=${OUT:-build/gpu/out}
mkdir -p "$OUT"
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
timeout -k 30 "$left" python3 eval/train_pruner.py "$@" --device cuda 2>&1 | tr '\r' '\n' > "$OUT/train.log"
tail -n 20 "$OUT/train.log"
[ -f "$run_dir/pruner_state.pt" ] && split -b 15M -d "$run_dir/pruner_state.pt" "$OUT/state.part"
[ -z "$out" ] || cp "$out.json" "$OUT/" 2>/dev/null
ls -la "$OUT"
