#!/usr/bin/env bash
# The image table (issue 5) on the bundled digits DiT, from scratch or resuming: every step whose output
# exists is skipped (FORCE=1 redoes them). ~2 h on 2 CPU cores. Writes results/image/*.{npz,json,png},
# results/image/TABLE.md and the README's image table.
set -euo pipefail
source "$(dirname "$0")/env.sh"
RHO=0.8
run() {  # run NAME ARGS...: one eval/imagenet.py run (2 processes), skipped if its JSON exists
  local name=$1; shift
  if [ -f "results/image/digits_${name}.json" ] && [ -z "${FORCE:-}" ]; then echo "[skip] $name"; return; fi
  echo "[run] $name $*"; bash scripts/image_run.sh "$name" "$@"
}
[ -f data/digits16.npz ] || python eval/train_dit.py --export-ref data/digits16.npz
run dense --method dense
run fora_n5 --method fora --fora-n 5
run taylorseer_n5_o2 --method taylorseer --fora-n 5 --taylor-order 2
run toca_n6 --method toca --fora-n 6 --sparsity $RHO
run duca_n6 --method duca --fora-n 6 --sparsity $RHO
[ -f results/schedules/digits_bac_$RHO.json ] || python eval/search_static.py --dit checkpoints/digits_dit \
    --sparsity $RHO --steps 50 --cfg 1.5 --out results/schedules/digits_bac_$RHO.json
run static_bac --method static --plan results/schedules/digits_bac_$RHO.json
# the learned pruner (TTS), started from the FORA interval (the searched per-branch schedule samples
# badly on this model, see the table), trained with exact-budget straight-through gates (resumable)
train_pruner() {  # train_pruner NAME ARGS...: skipped if its checkpoint exists
  local name=$1; shift
  if [ -f "checkpoints/pruners/${name}.json" ] && [ -z "${FORCE:-}" ]; then echo "[skip] $name"; return; fi
  python eval/train_image_pruner.py --model checkpoints/digits_dit --out "checkpoints/pruners/${name}" \
      --sparsity $RHO --prior every_n:5 --val-mode budget --n-train 128 --n-val 32 --epochs 3 \
      --threads 2 --run-dir "runs/${name}" --resume "$@"
}
train_pruner digits_tts_budget_$RHO --train-budget --prior-margin 0.5 --lr 6e-3
run tts --method tts --pruner checkpoints/pruners/digits_tts_budget_$RHO --sparsity $RHO
# beyond the paper: a pruner run with a TaylorSeer-style forecast of timestep reuse. Plain STE
# training (lr 3e-4) left it at its FORA start; with budget gates and lr 2e-2 the forecasts of
# irregular compute gaps diverged (logs in the README), so this row is the prior's schedule.
train_pruner digits_tts_taylor2_$RHO --forecast 2 --lr 3e-4
run tts_taylor2 --method tts --pruner checkpoints/pruners/digits_tts_taylor2_$RHO --sparsity $RHO --forecast 2
# whole steps placed by output error (one compute-step set for every branch, Taylor O=2), and the
# step-level pruner (--tie-branches) started from it: per-class/per-half step choices, exact budget
[ -f results/schedules/digits_steps_$RHO.json ] || python eval/search_static.py --dit checkpoints/digits_dit \
    --sparsity $RHO --steps 50 --cfg 1.5 --objective output --forecast 2 --calls 64 --batch 64 \
    --out results/schedules/digits_steps_$RHO.json
run steps_o2 --method static --plan results/schedules/digits_steps_$RHO.json --forecast 2
train_pruner digits_tts_steps_$RHO --prior results/schedules/digits_steps_$RHO.json --tie-branches --forecast 2 \
    --train-budget --prior-margin 0.5 --lr 3e-3
run tts_steps_o2 --method tts --pruner checkpoints/pruners/digits_tts_steps_$RHO --sparsity $RHO --forecast 2
# diffusers' own caches (diffusers.hooks) on the same model converted to diffusers' DiTTransformer2DModel
# (tts.adapters.dit_diffusers): First Block Cache at the threshold calibrated to RHO on seed-1 noise,
# TaylorSeer on every block's attn1 + ff (FORA's interval 5 after diffusers' 1-step warm-up, order 2)
run diffusers_fbc --method diffusers_fbc --sparsity $RHO
run diffusers_taylorseer_n5_o2 --method diffusers_taylorseer --fora-n 5 --taylor-order 2
has_rows() {  # latency.json exists and has a row for every method named
  python -c "import json, sys; r = json.load(open('results/image/latency.json'))['rows'][0]['methods']; \
sys.exit(not set(sys.argv[1:]) <= set(r))" "$@" 2>/dev/null
}
has_rows diffusers_fbc diffusers_taylorseer_n5_o2 && [ -z "${FORCE:-}" ] || python eval/image_latency.py --model checkpoints/digits_dit \
    --pruner checkpoints/pruners/digits_tts_budget_$RHO --pruner-taylor checkpoints/pruners/digits_tts_taylor2_$RHO \
    --pruner-steps checkpoints/pruners/digits_tts_steps_$RHO --plan-steps results/schedules/digits_steps_$RHO.json \
    --plan results/schedules/digits_bac_$RHO.json --sparsity $RHO --out results/image/latency.json
python eval/tables.py
