#!/usr/bin/env bash
# What the reuse steps of a 93% call cost: the call timed against DDIM with the same number of computed
# steps (ddim:matched), in one process, interleaved, at batch 1 and 28, one thread, Lift policy; the
# breakdown (encoder, pruner, wait, computed and reuse steps, engine, scheduler) is in each row.
# The pruner runs before step 0 (--parallel off: on a CPU with few cores a worker thread contends for the GIL with
# step 0 and waits longer than the pruner takes). About 3 min on a quiet machine (pause other jobs: timings share the cores). Then python eval/tables.py
#   bash recipes/reuse_cost.sh
set -euo pipefail
source "$(dirname "$0")/lib.sh"
robot_task lift
for method in file:results/schedules/lift_steps_0.93.json pruner:checkpoints/pruners/lift_tts_0.93@0.93; do
  python eval/latency.py --task lift --checkpoint "$CKPT" --trajectories "$TRAJ" --method "$method" \
    --reference ddim:matched --batch 1 28 --trials "${TRIALS:-5}" --frames 4 --threads 1 --parallel off
done
