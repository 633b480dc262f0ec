#!/usr/bin/env bash
# The visuomotor (camera) policy of TASK (default lift): the scripted expert's demonstrations
# (eval/collect_demos.py, with their MuJoCo states), their camera frames rendered once into robomimic's
# image layout (eval/render_demos.py: agentview and wrist cameras, 84x84; about 0.1 s per frame on 2
# CPU cores), the image DP-T trained on them (eval/train_policy.py --obs-type image: ResNet-18 trunk of
# width ENCODER_WIDTH, default 16, random 76x76 crops, the proprioception keys; STEPS default 6000 at
# batch 64, resumable), its dense success on the test seeds (rendering every env step), 16 recorded
# trajectories with their camera windows, and the call latency at batch 1 and 28 with its breakdown
# (image encoder, condition, steps; run on a quiet machine) for dense against 93% uniform timestep
# reuse and against DDIM-7. Every stage is skipped when its output exists. Hours on 2 CPU cores; then
# python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
TASK=${TASK:-lift}
data=data/${TASK}_expert.hdf5
images=data/${TASK}_expert_image.hdf5
CKPT=checkpoints/${TASK}_image_dpt
[ -f "$data" ] || python eval/collect_demos.py --task "$TASK" --episodes 100 --seed 0 --out "$data"
[ -f "$images" ] || python eval/render_demos.py --data "$data" --out "$images" --size 84 --threads "${THREADS:-2}"
[ -f "$CKPT.json" ] || python eval/train_policy.py --data "$images" --obs-type image \
    --encoder-width "${ENCODER_WIDTH:-16}" --steps "${STEPS:-6000}" --batch 64 --save-every 100 --out "$CKPT" --resume \
    --threads "${THREADS:-2}"
evaluate --method dense --n-envs 10
TRAJ=data/trajectories/$(basename "$CKPT").pt
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 16 \
    --out "$TRAJ" --resume --threads "${THREADS:-2}"
for m in uniform:0.93:timestep ddim:7; do
  python eval/latency.py --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" --method "$m" \
      --first-episode 0 --batch 1 28 --resume --threads "${THREADS:-2}"
done
python eval/tables.py
