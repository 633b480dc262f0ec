#!/usr/bin/env bash
# The Push-T testbed from scratch: MH-style data from the six scripted operators (resumes per
# operator), its multimodality figure, a DP-T policy (resumes from runs/), then dense and the
# few-step samplers on validation seeds (recipes/steps_matter.sh; STAGE=test for the test seeds).
#   bash recipes/pusht_testbed.sh        # about 25 min data, 45 min training, 20 min evaluation (2 cores)
# Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
[ -f data/pusht_mh.hdf5 ] || python eval/collect_demos.py --task pusht --mix mh --episodes 80 --seed 0 \
    --out data/pusht_mh.hdf5
[ -f docs/pusht_mh_modes.png ] || python eval/demo_modes.py --task pusht --data data/pusht_mh.hdf5
[ -f checkpoints/pusht_mh_dpt.json ] || python eval/train_policy.py --data data/pusht_mh.hdf5 \
    --out checkpoints/pusht_mh_dpt --steps 7000 --batch 128 --seed 0 --threads "${THREADS:-1}" --resume
TASK=pusht CKPT=checkpoints/pusht_mh_dpt bash "$(dirname "$0")/steps_matter.sh"
