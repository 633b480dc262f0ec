#!/usr/bin/env bash
# The image table on the bundled digits DiT, from scratch or resuming: every step whose output exists is
# skipped (FORCE=1 redoes them). About 2 h on 2 CPU cores. Writes results/image/*.{npz,json,png}, then
# docs/results/image.md and the README's image table (eval/tables.py).
set -euo pipefail
source "$(dirname "$0")/lib.sh"
RHO=0.8
run() {  # run METHOD [ARGS...]: one eval/imagenet.py run (2 processes), skipped if its JSON exists
  local slug
  slug=$(python -c "import sys; sys.path.insert(0, 'eval'); from common.methods import parse_method; \
print(parse_method(sys.argv[1]).slug)" "$1")
  if [ -f "results/image/digits_${slug}.json" ] && [ -z "${FORCE:-}" ]; then echo "[skip] $1"; return; fi
  echo "[run] $*"; bash "$(dirname "$0")/image_run.sh" "$@"
}
train_pruner() {  # train_pruner NAME ARGS...: skipped if its training finished
  local name=$1; shift
  if trained "$name" && [ -z "${FORCE:-}" ]; then echo "[skip] $name"; return; fi
  python eval/train_image_pruner.py --model checkpoints/digits_dit --out "checkpoints/pruners/${name}" \
      --sparsity $RHO --prior every_n:5 --val-mode budget --n-train 128 --n-val 32 --epochs 3 \
      --threads 2 --run-dir "$(state_dir "$name")" --resume "$@" && finish_state "$name"
}
bac=results/schedules/digits_bac_$RHO.json
steps=results/schedules/digits_steps_$RHO.json
[ -f data/digits16.npz ] || python eval/train_dit.py --export-ref data/digits16.npz
run dense
run every_n:5:timestep
run taylorseer:5:2
run toca:6@$RHO
run duca:6@$RHO
[ -f "$bac" ] || python eval/search_static.py --dit checkpoints/digits_dit --sparsity $RHO --steps 50 --cfg 1.5 \
    --out "$bac"
run "file:$bac"
train_pruner digits_tts_$RHO --train-budget --prior-margin 0.5 --lr 6e-3
run "pruner:checkpoints/pruners/digits_tts_$RHO@$RHO"
train_pruner digits_tts_taylor2_$RHO --forecast 2 --lr 3e-4
run "pruner:checkpoints/pruners/digits_tts_taylor2_$RHO@$RHO+taylor2"
[ -f "$steps" ] || python eval/search_static.py --dit checkpoints/digits_dit --sparsity $RHO --steps 50 --cfg 1.5 \
    --objective output --forecast 2 --calls 64 --batch 64 --out "$steps"
run "file:$steps+taylor2"
train_pruner digits_tts_steps_$RHO --prior "$steps" --tie-branches --forecast 2 --train-budget --prior-margin 0.5 \
    --lr 3e-3
run "pruner:checkpoints/pruners/digits_tts_steps_$RHO@$RHO+taylor2"
run diffusers:fbc@$RHO
run diffusers:taylorseer:5:2
methods=(every_n:5:timestep taylorseer:5:2 "toca:6@$RHO" "duca:6@$RHO" "file:$bac" "file:$bac+taylor2"
         "pruner:checkpoints/pruners/digits_tts_$RHO@$RHO"
         "pruner:checkpoints/pruners/digits_tts_taylor2_$RHO@$RHO+taylor2" "file:$steps+taylor2"
         "pruner:checkpoints/pruners/digits_tts_steps_$RHO@$RHO+taylor2" "diffusers:fbc@$RHO" diffusers:taylorseer:5:2)
[ -f results/image/latency.json ] && [ -z "${FORCE:-}" ] || python eval/image_latency.py \
    --model checkpoints/digits_dit --methods "${methods[@]}" --out results/image/latency.json
python eval/tables.py
