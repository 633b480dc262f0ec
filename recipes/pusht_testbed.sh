#!/usr/bin/env bash
# The Push-T testbed from scratch: MH-style data from the six scripted operators (resumes per
# operator), its multimodality figure, a DP-T policy (resumes from its state_dir) and the same policy trained
# 10000 steps more (warm start), dense and the few-step samplers on validation seeds
# (recipes/steps_matter.sh), then for the longer-trained policy: the test seeds for dense, the
# 3- and 7-step samplers and 93% reuse, its full-horizon trajectories and searched steps at 93%; and its
# counterpart whose last 10000 steps train with the reference's dropout 0.3 (instead of 0.1).
#   bash recipes/pusht_testbed.sh   # about 25 min data, 2 h training, 1.5 h evaluation (2 cores)
# Then python eval/tables.py; the Table 7 shape on it: TASK=pusht CKPT=checkpoints/pusht_mh_dpt_17k
# ALL_EPISODES=1 bash recipes/table7.sh
set -euo pipefail
source "$(dirname "$0")/lib.sh"
[ -f data/pusht_mh.hdf5 ] || python eval/collect_demos.py --task pusht --mix mh --episodes 80 --seed 0 \
    --out data/pusht_mh.hdf5
[ -f docs/pusht_mh_modes.png ] || python eval/demo_modes.py --task pusht --data data/pusht_mh.hdf5
[ -f checkpoints/pusht_mh_dpt.json ] || { python eval/train_policy.py --data data/pusht_mh.hdf5 \
    --out checkpoints/pusht_mh_dpt --steps 7000 --batch 128 --seed 0 --threads "${THREADS:-1}" --resume \
    --run-dir "$(state_dir pusht_mh_dpt)" && finish_state pusht_mh_dpt; }
TASK=pusht CKPT=checkpoints/pusht_mh_dpt bash "$(dirname "$0")/steps_matter.sh"
long=checkpoints/pusht_mh_dpt_17k
[ -f "$long.json" ] || { python eval/train_policy.py --data data/pusht_mh.hdf5 --init checkpoints/pusht_mh_dpt \
    --out "$long" --steps 10000 --batch 128 --seed 1 --threads "${THREADS:-1}" --resume \
    --run-dir "$(state_dir "${long##*/}")" && finish_state "${long##*/}"; }
TASK=pusht CKPT=$long KS="3 7 10" TRAILING_KS=3 DPM_KS="3 7" bash "$(dirname "$0")/steps_matter.sh"
robot_task pusht
CKPT=$long
TRAJ=data/trajectories/pusht-$(basename "$long")_full.pt
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task pusht --checkpoint "$CKPT" --episodes 112 \
    --full-horizon --out "$TRAJ" --threads "${THREADS:-1}" --resume
steps=results/schedules/pusht-$(basename "$long")_steps_0.93.json
ALL_EPISODES=1 search_steps "$steps" 0.93
for m in dense ddim:3 ddim:3:trailing ddim:7 dpm:3 dpm:7 uniform:0.93:timestep "file:$steps"; do
  evaluate --method "$m" --threads "${THREADS:-1}"
done
[ -f checkpoints/pusht_mh_dpt_17k_dropout0.3.json ] || { python eval/train_policy.py --data data/pusht_mh.hdf5 \
    --init checkpoints/pusht_mh_dpt --dropout 0.3 --out checkpoints/pusht_mh_dpt_17k_dropout0.3 --steps 10000 \
    --batch 128 --seed 1 --threads "${THREADS:-1}" --resume --run-dir "$(state_dir pusht_mh_dpt_17k_dropout0.3)" \
    && finish_state pusht_mh_dpt_17k_dropout0.3; }
