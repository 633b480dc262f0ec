#!/usr/bin/env bash
# The reference trains its policies with dropout 0.3 on every residual branch, which should make a
# reused (stale) branch output less harmful. This recipe trains the MH-style Lift policy's twin with
# dropout 0.3 instead of 0.1 (same data, steps, batch and seed as checkpoints/lift_mh_dpt; resumable
# from its state_dir) and runs the Table 7 static rows on it (recipes/table7.sh PARTS=statics).
#   bash recipes/lift_mh_dropout.sh   # about 40 min training on one thread, then the rows (hours)
# THREADS: torch threads (default 1). Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
name=lift_mh_dpt_dropout0.3
[ -f "checkpoints/$name.json" ] || [ -f data/lift_mh.hdf5 ] || python eval/collect_demos.py --task lift --mix mh \
    --episodes 100 --seed 0 --out data/lift_mh.hdf5  # the demonstrations, only for a policy still to train
[ -f "checkpoints/$name.json" ] || { python eval/train_policy.py --data data/lift_mh.hdf5 --dropout 0.3 \
    --out "checkpoints/$name" --steps 7000 --batch 128 --seed 0 --threads "${THREADS:-1}" --resume \
    --run-dir "$(state_dir "$name")" && finish_state "$name"; }
TASK=lift CKPT=checkpoints/$name PARTS=statics THREADS=${THREADS:-1} bash "$(dirname "$0")/table7.sh"
