#!/usr/bin/env bash
# Does the number of denoising steps matter for a policy? Dense DDPM-100 and DDIM-k for k in KS
# (default 1 2 3 5 7 10; Diffusion Policy's leading timesteps), then the stronger few-step samplers a
# user would try: DDIM with trailing timesteps (starts at t = 99) for k in TRAILING_KS (default 2 3 5)
# DPM-Solver++ for k in DPM_KS (default 2 3 5 7) and the policy's own stochastic DDPM on k leading
# timesteps for k in DDPM_KS (default 3 7 10; an empty list, e.g. KS="", skips that family), first on validation seeds (400000.., never a test seed), then, with
# STAGE=test, on the 3 test seeds x 50 episodes. The testbed counts as discriminative for a task
# when dense success is high and DDIM-3 falls more than 10 points below it.
#   TASK=lift CKPT=checkpoints/lift_mh_dpt bash recipes/steps_matter.sh
# THREADS: torch threads (default 1: success runs, not timings). Resumable (robot.py --resume). About 5-15 min per method and seed on 2 CPU cores. Then:
# python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
ckpt=${CKPT:-}
robot_task "${TASK:-lift}"
CKPT=${ckpt:-$CKPT}
if [ "${STAGE:-val}" = val ]; then
  export SEEDS=${SEEDS:-400000}
fi
evaluate --method dense --threads "${THREADS:-1}"
for k in ${KS-1 2 3 5 7 10}; do
  evaluate --method "ddim:$k" --threads "${THREADS:-1}"
done
for k in ${TRAILING_KS-2 3 5}; do
  evaluate --method "ddim:$k:trailing" --threads "${THREADS:-1}"
done
for k in ${DPM_KS-2 3 5 7}; do
  evaluate --method "dpm:$k" --threads "${THREADS:-1}"
done
for k in ${DDPM_KS-3 7 10}; do
  evaluate --method "ddpm:$k" --threads "${THREADS:-1}"
done
