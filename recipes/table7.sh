#!/usr/bin/env bash
# The paper's Table 7 shape at 93% on one policy (TASK, CKPT; default the MH-style Lift policy), on the
# test seeds, every row paired with dense on the same episodes. PARTS picks the stages (default all;
# STATICS="dense dpm:7 file:STEPS ..." runs only those static rows, file:STEPS / file:EARLY standing
# for the searched steps and their rollout-early variant):
#   statics   dense; the few-step samplers; the searched static whole steps; one reuse direction at a
#             time as uniform static plans (forward, timestep, rollout), rollout with the compute steps
#             rotating per call (every slot refreshed), and the searched steps with rollout reuse on
#             the high-noise steps 0-49 and timestep reuse after; the age of the reused rollout slots
#   pruners   TTS pruners with the reference recipe (eval/train_pruner.py --recipe reference: hidden 512,
#             8 heads, FF 1024, head bias zero, AdamW 1e-4, 20 epochs, batches of 16 full-horizon
#             episodes, unpaired noise), from scratch for each direction set (forward / timestep /
#             rollout / all three) and, for all three, from the searched prior; the pruner's
#             forward/backward in bfloat16 autocast where the device has bfloat16 arithmetic (a GPU,
#             or a CPU with avx512_bf16 / amx_bf16; elsewhere autocast emulates it, about 25x slower)
#             and in float32 otherwise (PRECISION sets it; a resumed run may change it); and
#             omni-paired: the omni recipe with the dense call's own noise as target (--paired),
#             whose loss no longer rewards an action between the modes. A
#             reference-length training is hours on 2 CPU cores (on a GPU, DEVICE=cuda); each resumes from its state_dir (recipes/lib.sh) after
#             an interruption, and `touch checkpoints/in_progress/<pruner name>/STOP` stops it (and the
#             recipe) right after its next saved group. PRUNERS picks
#             some of "omni prior forward timestep rollout omni-paired" (e.g. two at once with THREADS=1 each)
#   analysis  the prior pruner's agreement with the prior on held-out episodes, the oracle headroom
#             around the searched steps, the spread of each finished row's actions across noise draws
#             (eval/sample_spread.py), the mask and rollout-feature-similarity figures, the
#             pruners' training curves (also of trainings in progress)
# Every step is skipped when its output exists. The steps are searched on the successful recorded
# episodes (ALL_EPISODES=1: on all of them, for Push-T, whose policy rarely succeeds); the rollout
# ages, the pruners and the analysis take every recorded episode, as the reference runs its episodes
# to the full horizon whatever their outcome (an MH-style policy fails some episodes, and the
# successful ones alone may leave none to hold out). THREADS: torch threads of every step (default
# 2; 1 next to another job).
# Then python eval/tables.py
set -euo pipefail
source "$(dirname "$0")/lib.sh"
ckpt=${CKPT:-checkpoints/lift_mh_dpt}
robot_task "${TASK:-lift}"
CKPT=$ckpt
policy=${TASK}-$(basename "$CKPT")
parts=${PARTS:-statics,pruners,analysis}
TRAJ=data/trajectories/${policy}_full.pt
steps=results/schedules/${policy}_steps_0.93.json
early=results/schedules/${policy}_steps_0.93_rollout_early.json
# need_steps: the 112 full-horizon trajectories, the searched steps and their rollout-early variant,
# made on first use only, so the rows that need none of them run first on a new checkout. While a
# column's pruners train, commit its trajectories (git add -f "$TRAJ", about 5 MB): collected again on
# another checkout, round-off changes some rollouts, and a resumed run would train on other episodes.
need_steps() {
  [ -f "$TRAJ" ] || python eval/collect_trajectories.py --task "$TASK" --checkpoint "$CKPT" --episodes 112 \
      --full-horizon --out "$TRAJ" --resume --threads "${THREADS:-2}"
  search_steps "$steps" 0.93
  [ -f "$early" ] || python eval/derive_schedule.py "$steps" --early rollout --until 50 --out "$early"
}
omni=${policy}_reference_forward-timestep-rollout_0.93
prior=${policy}_reference_prior_0.93
if [[ $parts == *statics* ]]; then
  # shellcheck disable=SC2206
  statics=(${STATICS:-dense ddim:7 ddim:3 ddim:3:trailing dpm:3 dpm:7 uniform:0.93:forward \
           uniform:0.93:timestep uniform:0.93:rollout rotating:0.93:rollout file:STEPS file:EARLY})
  for m in "${statics[@]}"; do
    [[ $m != file:* ]] || need_steps
    m=${m/file:STEPS/file:$steps}
    evaluate --method "${m/file:EARLY/file:$early}"
  done
  [ -n "${STATICS:-}" ] || [ -f "results/robot/rollout_age_${policy}.json" ] || { need_steps; python eval/rollout_age.py \
      --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" \
      --methods uniform:0.93:rollout rotating:0.93:rollout "file:$early" --all-episodes; }
fi
# The reference's sparsity weight (lam 1) balances an L1 on actions in [-1, 1] (robosuite's). Push-T's
# actions are pixel targets (0-512), whose L1 is hundreds of times larger and would drown the sparsity
# term, so its pruners take the L1 on the policy's normalised actions, which are in [-1, 1].
loss_space=$([ "$TASK" = pusht ] && echo normalized || echo raw)
precision=${PRECISION:-$({ [ -n "${DEVICE:-}" ] || grep -qE 'avx512_bf16|amx_bf16' /proc/cpuinfo; } && echo bfloat16 || echo float32)}
reference_pruner() {  # NAME DIRECTIONS [ARGS...]: the reference recipe on 96 train / 16 validation episodes
  local name=$1 dirs=$2; shift 2
  trained "$name" || { python eval/train_pruner.py --recipe reference --trajectories "$TRAJ" \
      --checkpoint "$CKPT" --out "checkpoints/pruners/$name" --directions "$dirs" --sparsity 0.93 \
      --n-train 96 --n-val 16 --precision "$precision" --loss-space "$loss_space" \
      --threads "${THREADS:-2}" ${DEVICE:+--device "$DEVICE"} \
      --run-dir "$(state_dir "$name")" --resume --all-episodes "$@" && finish_state "$name"; }
}
if [[ $parts == *pruners* || $parts == *analysis* ]]; then need_steps; fi
if [[ $parts == *pruners* ]]; then
  for which in ${PRUNERS:-omni prior forward timestep rollout}; do
    case $which in
      omni) reference_pruner "$omni" forward,timestep,rollout; name=$omni ;;
      prior) reference_pruner "$prior" forward,timestep,rollout --prior "$steps"; name=$prior ;;
      omni-paired) name=${policy}_reference_paired_forward-timestep-rollout_0.93
        reference_pruner "$name" forward,timestep,rollout --paired ;;
      forward|timestep|rollout) name=${policy}_reference_${which}_0.93; reference_pruner "$name" "$which" ;;
      *) echo "PRUNERS: unknown pruner $which (omni, omni-paired, prior, forward, timestep, rollout)" >&2; exit 2 ;;
    esac
    evaluate --method "pruner:checkpoints/pruners/$name"
  done
fi
if [[ $parts == *analysis* ]]; then
  ALL_EPISODES=1 headroom "$steps"
  [ -f "docs/${policy}_feature_similarity.png" ] || python eval/figures.py similarity --task "$TASK" \
      --checkpoint "$CKPT" --trajectories "$TRAJ" --all-episodes
  ! trained "$prior" || [ -f "results/robot/agreement_${TASK}_$prior.json" ] \
      || python eval/pruner_agreement.py --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" \
      --pruner "checkpoints/pruners/$prior" --all-episodes
  spread=(dense ddim:3:trailing dpm:3 dpm:7 "file:$steps")
  for name in "$omni" "$prior" "${policy}_reference_paired_forward-timestep-rollout_0.93" \
      "${policy}_reference_"{forward,timestep,rollout}_0.93; do
    ! trained "$name" || spread+=("pruner:checkpoints/pruners/$name")
  done
  python eval/sample_spread.py --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" --methods "${spread[@]}" \
      --threads "${THREADS:-2}" --resume --all-episodes
  ! compgen -G "checkpoints/pruners/${policy}_reference_*.json" >/dev/null \
      || python eval/figures.py training-curves --task "$TASK" --checkpoint "$CKPT"
  ! trained "$omni" || [ -f "docs/${policy}_pruning_masks.png" ] \
      || python eval/figures.py masks --task "$TASK" --checkpoint "$CKPT" --trajectories "$TRAJ" \
      --pruner "checkpoints/pruners/$omni" --all-episodes
fi
python eval/tables.py
