#!/usr/bin/env bash
# One image-table run: bash recipes/image_run.sh METHOD [eval/imagenet.py args...]
# Samples 2000 digits with NPROC processes (accelerate launch; default 2) into
# results/image/digits_<method slug>.npz and scores FID/sFID against the digits set.
set -euo pipefail
source "$(dirname "$0")/../scripts/env.sh"
method=$1; shift
slug=$(python -c "import sys; sys.path.insert(0, 'eval'); from common.methods import parse_method; \
print(parse_method(sys.argv[1]).slug)" "$method")
mkdir -p results/image data
nproc=${NPROC:-2}
exec accelerate launch $([ "$nproc" -gt 1 ] && echo --multi_gpu) --num_processes "$nproc" eval/imagenet.py --model checkpoints/digits_dit \
    --method "$method" --steps 50 --cfg 1.5 --num-samples 2000 --ref data/digits16.npz \
    --ref-cache data/digits16_stats.npz --out "results/image/digits_${slug}.npz" --no-progress "$@"
