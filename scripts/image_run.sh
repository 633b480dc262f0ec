#!/usr/bin/env bash
# One image-table run: bash scripts/image_run.sh NAME [eval/imagenet.py args...]
# Samples 2000 digits with 2 processes (accelerate launch) and scores FID/sFID against the digits set.
set -euo pipefail
source "$(dirname "$0")/env.sh"
name=$1; shift
mkdir -p results/image data
exec accelerate launch --multi_gpu --num_processes 2 eval/imagenet.py --model checkpoints/digits_dit \
    --steps 50 --cfg 1.5 --num-samples 2000 --ref data/digits16.npz --ref-cache data/digits16_stats.npz \
    --out "results/image/digits_${name}.npz" --no-progress "$@"
