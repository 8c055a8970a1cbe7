#!/usr/bin/env bash
# The noise-robust default (issue 29), in two device calls. Stage `teachers`: one demonstration set,
# then two `decay` runs of 3 seeds side by side on one GPU, each trained on a noisy, biased needle
# observation (domain randomisation: sigma ~ U[0, obs_noise_mm], bias ~ U[0, obs_bias_mm] per
# environment and iteration). Stage `students`: each teacher seed taught a 2x256 student by DAgger,
# the student acting on a noisy needle, the teacher labelling the true state; the student's
# iteration chosen on validation problems of its own seed under the same noise.
#
#   bash experiments/robust_recipe.sh teachers runs/robust
#   bash experiments/robust_recipe.sh students runs/robust
#   bash experiments/robust_recipe.sh students2 runs/robust  # students aiming deeper into the goal; choice on validation
#   bash experiments/robust_recipe.sh general runs/robust    # the generalist: train and distil, one call
set -euo pipefail
stage=$1
out=${2:-runs/robust}
mkdir -p "$out"
# teachers: name noise_mm bias_mm
teachers=("n05 0.5 0.25" "n10 1.0 0.5")
case "$stage" in
teachers)
  python -m regrasp_mjx.demos --n 9900 --seed 0 --workers "$(($(nproc) - 1))" --out "$out/demos" --quiet
  for t in "${teachers[@]}"; do
    read -r name noise bias <<< "$t"
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 python -m regrasp_mjx.train --preset decay --seeds 3 --demos "$out/demos" \
      --set obs_noise_mm="$noise" --set obs_bias_mm="$bias" --set checkpoint_every=1000 --set planner_workers=7 \
      --out "$out/$name" > "$out/$name.log" 2>&1 &
  done
  wait
  ;;
students)
  # students: teacher noise_mm bias_mm (what the student acts under)
  for t in "${teachers[@]}"; do
    read -r name noise bias <<< "$t"
    for s in 0 1 2; do
      XLA_PYTHON_CLIENT_MEM_FRACTION=0.15 python -m regrasp_mjx.distill --teacher "$out/$name/seed$s/policy" \
        --out "$out/student_$name/s$s" --seed "$s" --set "hidden=(256,256)" --set iterations=20 \
        --set obs_noise_mm="$noise" --set obs_bias_mm="$bias" > "$out/student_${name}_s$s.log" 2>&1 &
    done
  done
  wait
  ;;
students2)
  # students aiming inside 0.7 of the success tolerances (distill.goal_tolerance), from the n05 teachers,
  # under the teachers' noise (n05) and more (n075); then every student's robustness on validation
  # problems of their own seed (1000, seed 7000001): the choice, never a test set
  for v in "t07 0.5 0.25" "t07n075 0.75 0.35"; do
    read -r name noise bias <<< "$v"
    for s in 0 1 2; do
      XLA_PYTHON_CLIENT_MEM_FRACTION=0.12 timeout "${DISTILL_TIMEOUT:-330}" python -m regrasp_mjx.distill \
        --teacher "$out/n05/seed$s/policy" --out "$out/student_$name/s$s" --seed "$s" --set "hidden=(256,256)" \
        --set iterations=20 --set obs_noise_mm="$noise" --set obs_bias_mm="$bias" --set goal_tolerance=0.7 \
        > "$out/student_${name}_s$s.log" 2>&1 &
    done
  done
  wait
  policies=()
  for d in "$out"/student_*/s*/policy; do
    n=${d#"$out"/student_}; policies+=(--policy "${n%/policy}=$d"); done
  python experiments/robustness.py "${policies[@]}" --heldout 1000:7000001 --modes "open,per-frame 0.7,fused" \
    --conditions "exact,sigma 0.25 mm,sigma 0.5 mm,bias 0.25 mm + sigma 0.25 mm" --out "$out/select" --name select
  ;;
general)
  # the generalist: `general` with the same noise, then 3x256 students under it (one device call)
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.6 timeout "${TRAIN_TIMEOUT:-420}" python -m regrasp_mjx.train --preset general --seeds 3 \
    --set obs_noise_mm=0.5 --set obs_bias_mm=0.25 --set checkpoint_every=1000 --testset general1000 --out "$out/general" > "$out/general.log" 2>&1
  for s in 0 1 2; do
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.12 timeout "${DISTILL_TIMEOUT:-170}" python -m regrasp_mjx.distill \
      --teacher "$out/general/seed$s/policy" --out "$out/student_general/s$s" --seed "$s" --testset general1000 \
      --set "hidden=(256,256,256)" --set iterations=20 --set obs_noise_mm=0.5 --set obs_bias_mm=0.25 \
      > "$out/student_general_s$s.log" 2>&1 &
  done
  wait
  ;;
*)
  echo "usage: $0 teachers|students|general OUT" >&2
  exit 2
  ;;
esac
