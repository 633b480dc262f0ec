#!/usr/bin/env bash
# The image frontier on the bundled digits DiT: FID (2000 samples, with its bootstrap 95% interval) and
# sFID against sampling latency, every method timed against dense DDIM-50 in one process
# (eval/image_latency.py, batch 1 and 16). Fewer-step samplers: DDIM-k and DPM-Solver++-k (k = 5 8 10 15
# 20). On the 50-step base: FORA (every_n:N, N = 2 3 5), TaylorSeer (N = 3 5, order 2), ToCa and DuCa
# (RHO 0.6, 0.8), the searched steps and the TTS step pruner (order-2 forecasting) served at RHO 0.6-0.9.
# On the 20-step base (+ddim:20): FORA (N = 2 3), TaylorSeer (N = 3), ToCa and DuCa (0.6), the searched
# steps at RHO 0.5 and the TTS step pruner trained on them. A run is skipped when its JSON has a FID
# interval (one without it is redone). About 5-10 min per FID run on 2 quiet CPU cores (4-5 of
# them the Inception pass), hours in all; PARTS=runs,latency picks stages; NPROC=1 samples in one process
# (next to another job). The 20-step base's schedule and pruner are made when its first run comes. Then
# the figure docs/frontier_digits.png and eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
run() {  # run METHOD: one eval/imagenet.py run (image_run.sh), skipped when it has a FID interval
  local slug json
  slug=$(python -c "import sys; sys.path.insert(0, 'eval'); from common.methods import parse_method; \
print(parse_method(sys.argv[1]).slug)" "$1")
  json=results/image/digits_${slug}.json
  if [ -f "$json" ] && python -c "import json, sys; sys.exit(0 if json.load(open(sys.argv[1])).get('fid_interval') \
else 1)" "$json"; then echo "[skip] $1"; return; fi
  echo "[run] $1"; bash "$(dirname "$0")/image_run.sh" "$1"
}
steps50=results/schedules/digits_steps_0.8.json
steps20=results/schedules/digits_steps_ddim20_0.5.json
pruner50=checkpoints/pruners/digits_tts_steps_0.8
pruner20=digits_tts_steps_ddim20_0.5
[ -f data/digits16.npz ] || python eval/train_dit.py --export-ref data/digits16.npz
[ -f "$steps50" ] || python eval/search_static.py --dit checkpoints/digits_dit --sparsity 0.8 --steps 50 --cfg 1.5 \
    --objective output --forecast 2 --calls 64 --batch 64 --out "$steps50"
base20() {  # the 20-step base's searched steps and the step pruner trained on them, on first use
  [ -f "$steps20" ] || python eval/search_static.py --dit checkpoints/digits_dit --sparsity 0.5 --steps 20 \
      --cfg 1.5 --objective output --forecast 2 --calls 64 --batch 64 --out "$steps20"
  trained "$pruner20" || { python eval/train_image_pruner.py --model checkpoints/digits_dit \
      --out "checkpoints/pruners/$pruner20" --steps 20 --sparsity 0.5 --prior "$steps20" --tie-branches --forecast 2 \
      --train-budget --prior-margin 0.5 --lr 3e-3 --val-mode budget --n-train 128 --n-val 32 --epochs 3 \
      --threads 2 --run-dir "$(state_dir "$pruner20")" --resume && finish_state "$pruner20"; }
}
# most telling first, so that a cut-off run still has the TTS points: the samplers, the sparse methods at
# 80% reuse on the 50-step base, the TTS step pruner at other budgets, the 20-step base, then the rest
methods=(dense)
for k in 5 8 10 15 20; do methods+=("ddim:$k"); done
for k in 10 15 20 8 5; do methods+=("dpm:$k"); done
for n in 2 3 5; do methods+=("every_n:$n:timestep"); done
methods+=(taylorseer:3:2 taylorseer:5:2 "file:$steps50+taylor2")
for rho in 0.8 0.9 0.7 0.6; do methods+=("pruner:$pruner50@$rho+taylor2"); done
methods+=("file:$steps20+taylor2+ddim:20" "pruner:checkpoints/pruners/$pruner20@0.5+taylor2+ddim:20"
          toca:6@0.8 duca:6@0.8 every_n:2:timestep+ddim:20 taylorseer:3:2+ddim:20 toca:6@0.6 duca:6@0.6
          toca:6@0.6+ddim:20 duca:6@0.6+ddim:20 every_n:3:timestep+ddim:20)
parts=${PARTS:-runs,latency}
if [[ $parts == *runs* ]]; then
  for m in "${methods[@]}"; do
    [[ $m != *$pruner20* && $m != *$steps20* ]] || base20
    run "$m"
  done
fi
if [[ $parts == *latency* ]]; then
  [ -f results/image/frontier_latency.json ] || python eval/image_latency.py --model checkpoints/digits_dit \
      --batch 1 16 --trials "${TRIALS:-5}" --methods "${methods[@]:1}" --out results/image/frontier_latency.json
fi
python eval/figures.py image-frontier
python eval/tables.py
