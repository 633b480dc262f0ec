#!/usr/bin/env bash
# Policy-call latencies on a GPU machine that has PyTorch but no project install and no network:
#   OUT=FOLDER bash scripts/gpu_latency.sh TASK CHECKPOINT TRAJECTORIES METHOD...
# For each METHOD, eval/latency.py against dense with its timing breakdown (batch 1 and 28, the
# recorded episodes from index 0; a pruner also with its side-stream overlap off), then
# eval/frontier_latency.py with every METHOD, DDIM-2..10 and DPM-Solver++-3/7 interleaved. Results go
# where the tools write them (results/robot/gpu/) and are packed, with the log, into OUT/gpu_results.tar
# after each run (a cut-off call still brings back what finished). The set-up is scripts/gpu_env.sh's.
set -uo pipefail
OUT=${OUT:-build/gpu/out}
mkdir -p "$OUT" results/robot/gpu
# shellcheck disable=SC1091
source "$(dirname "$0")/gpu_env.sh" || exit 3
task=$1 ckpt=$2 traj=$3
shift 3
common=(--task "$task" --checkpoint "$ckpt" --trajectories "$traj" --first-episode 0 --batch 1 28 --device cuda
        --resume)
declare -A seen
frontier=()
for m in ddim:2 ddim:3 ddim:5 ddim:7 ddim:10 dpm:3 dpm:7 "$@"; do
  [ -n "${seen[$m]:-}" ] || { seen[$m]=1; frontier+=("$m"); }
done
pack() { tar -cf "$OUT/gpu_results.tar" results/robot/gpu "$OUT/gpu.log" 2>/dev/null; }
{
  for m in "$@"; do
    python3 eval/latency.py "${common[@]}" --method "$m" --trials 3
    [[ $m != pruner:* ]] || python3 eval/latency.py "${common[@]}" --method "$m" --trials 3 --parallel off
    pack
  done
  python3 eval/frontier_latency.py "${common[@]}" --methods "${frontier[@]}"
} 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tee "$OUT/gpu.log"
pack
ls -la "$OUT"
