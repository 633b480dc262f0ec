#!/usr/bin/env bash
# The visuomotor (camera) policy of TASK (default lift): the scripted expert's demonstrations
# (eval/collect_demos.py, with their MuJoCo states), their camera frames rendered once into robomimic's
# image layout (eval/render_demos.py: agentview and wrist cameras, 84x84; about 0.15 s per frame on 2
# CPU cores), the image DP-T trained on them (eval/train_policy.py --obs-type image: ResNet-18 trunk of
# width ENCODER_WIDTH, default 16, random 76x76 crops, the proprioception keys; 6000 steps at batch 64
# (checkpoints/<task>_image_dpt), then MORE_STEPS (default
# 8000) more from those weights with a fresh learning-rate cycle (checkpoints/<task>_image_dpt_14k),
# and with FURTHER_STEPS (e.g. 8000) that many more again (checkpoints/<task>_image_dpt_22k), which
# then is the policy of every stage below; resumable; DEVICE=cuda trains on a GPU), 112 recorded trajectories with their camera windows (the
# schedule search's calibration calls, the pruner's 96 training and 16 validation episodes, the
# latency tools' observations), the searched 93% steps, and then three stages (PARTS, default
# pruner,success,latency; PARTS=train stops once the policy is trained):
# - pruner: the step-level TTS pruner at 93% as robot_table.sh trains it (recipes/lib.sh steps_recipe:
#   from the searched steps, timestep and rollout reuse, 3 epochs), trained on the recorded camera
#   windows of the successful episodes (16 of them for validation, the rest for training; a failed episode
#   runs 50 calls against about 7, and a lockstep group runs to its longest episode);
# - success: dense, the searched 93% steps, DDIM-7, DPM-Solver++-7, DDIM-3, DPM-Solver++-3, the
#   policy's own stochastic DDPM on 3 steps and the pruner (once
#   trained) on the test seeds, rendering the frames each call reads (about 0.5-1.5 h per method on 2 CPU cores);
# - latency: each of those and uniform 93% timestep reuse against dense at batch 1 and 28, with the
#   breakdown (image encoder, condition, pruner, wait, steps); run it on a quiet machine.
# Every stage is skipped when its output exists. Hours on 2 CPU cores. Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
TASK=${TASK:-lift}
data=data/${TASK}_expert.hdf5
images=data/${TASK}_expert_image.hdf5
first=checkpoints/${TASK}_image_dpt
CKPT=${first}_$(( (6000 + ${MORE_STEPS:-8000}) / 1000 ))k
# rendered_demos: the demonstrations and their camera frames, made only for a policy still to train.
rendered_demos() {
  [ -f "$data" ] || python eval/collect_demos.py --task "$TASK" --episodes 100 --seed 0 --out "$data"
  [ -f "$images" ] || python eval/render_demos.py --data "$data" --out "$images" --size 84 --threads "${THREADS:-2}"
}
# train_image OUT STEPS [--init CKPT]: a resumable image-policy training stretch, skipped when OUT exists.
train_image() {
  local out=$1 n=$2
  shift 2
  [ -f "$out.json" ] || { rendered_demos && python eval/train_policy.py --data "$images" --obs-type image "$@" \
      --encoder-width "${ENCODER_WIDTH:-16}" --steps "$n" --batch 64 --save-every 100 --out "$out" --resume \
      --run-dir "$(state_dir "${out##*/}")" ${DEVICE:+--device "$DEVICE"} --threads "${THREADS:-2}" && finish_state "${out##*/}"; }
}
train_image "$first" 6000
train_image "$CKPT" "${MORE_STEPS:-8000}" --init "$first"
if [ "${FURTHER_STEPS:-0}" -gt 0 ]; then  # a third stretch from the second's weights, fresh learning-rate cycle
  second=$CKPT
  CKPT=${first}_$(( (6000 + ${MORE_STEPS:-8000} + FURTHER_STEPS) / 1000 ))k
  train_image "$CKPT" "$FURTHER_STEPS" --init "$second"
fi
parts=${PARTS:-pruner,success,latency}
[ "$parts" != train ] || exit 0
TRAJ=data/trajectories/$(basename "$CKPT").pt
policy=${TASK}-$(basename "$CKPT")
steps=results/schedules/${policy}_steps_0.93.json
pruner=${policy}_tts_0.93
[[ $parts != *success* ]] || evaluate --method dense --n-envs 10
[ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 112 \
    --out "$TRAJ" --resume --threads "${THREADS:-2}"
search_steps "$steps" 0.93
methods=("file:$steps" ddim:7 dpm:7 ddim:3 dpm:3 ddpm:3)
# shellcheck disable=SC2046
[[ $parts != *pruner* ]] || NTRAIN=82 EPOCHS=3 train_named "$pruner" $(steps_recipe 0.93 "$steps") --directions timestep,rollout
if trained "$pruner"; then methods+=("pruner:checkpoints/pruners/$pruner@0.93"); fi
if [[ $parts == *success* ]]; then
  for m in "${methods[@]}"; do evaluate --method "$m" --n-envs 10; done
fi
if [[ $parts == *latency* ]]; then
  for m in "${methods[@]}" uniform:0.93:timestep; do
    python eval/latency.py --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" --method "$m" \
        --first-episode 0 --batch 1 28 --resume --threads "${THREADS:-2}"
  done
fi
python eval/tables.py
