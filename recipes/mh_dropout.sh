#!/usr/bin/env bash
# The reference trains its policies with dropout 0.3 on every residual branch, which should make a
# reused (stale) branch output less harmful. This recipe trains the twin of an MH-style policy
# (TASK=lift, default, or can) with dropout 0.3 instead of 0.1 (same data, steps, batch and seed as
# checkpoints/${TASK}_mh_dpt; resumable from its state_dir), then runs the Table 7 static rows on it
# (recipes/table7.sh PARTS=statics) unless PARTS says otherwise (e.g. PARTS=train: the policy only).
#   bash recipes/mh_dropout.sh            # about 45 min training on one thread, then the rows (hours)
#   TASK=can bash recipes/mh_dropout.sh
# THREADS: torch threads (default 1). Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
task=${TASK:-lift}
name=${task}_mh_dpt_dropout0.3
data=data/${task}_mh.hdf5
[ -f "checkpoints/$name.json" ] || [ -f "$data" ] || python eval/collect_demos.py --task "$task" --mix mh \
    --episodes 100 --seed 0 --out "$data"  # the demonstrations, only for a policy still to train
[ -f "checkpoints/$name.json" ] || { python eval/train_policy.py --data "$data" --dropout 0.3 \
    --out "checkpoints/$name" --steps 7000 --batch 128 --seed 0 --threads "${THREADS:-1}" --resume \
    --run-dir "$(state_dir "$name")" && finish_state "$name"; }
[ "${PARTS:-statics}" = train ] || TASK=$task CKPT=checkpoints/$name PARTS=statics THREADS=${THREADS:-1} \
    bash "$(dirname "$0")/table7.sh"
