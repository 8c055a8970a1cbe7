#!/usr/bin/env bash
# The robot-error rows of experiments/robot_errors.sh for the policies whose table files a first run did
# not bring back (its jobs 2-4), and the default's closed loop at more warm-up frames in the camera view
# (validation problems of seed 7000017, for the next selection; not shipped):
#   bash experiments/robot_errors_rest.sh OUT_DIR
set -euo pipefail
out=${1:?usage: robot_errors_rest.sh OUT_DIR}
conditions=$(python -c "from regrasp_mjx import robustness; print(','.join(c.name for c in robustness.ROBOT_CONDITIONS))")
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.3 PYTHONUNBUFFERED=1
jobs=(
  "2 0 --policy general --policy general_v1"
  "3 1 --policy student_v1 --policy student_v2"
  "4 0 --policy default --heldout 3000:2022 --no-testset"
)
for job in "${jobs[@]}"; do
  read -r i gpu args <<< "$job"
  CUDA_VISIBLE_DEVICES=$gpu python -m regrasp_mjx.compare --robustness --conditions "$conditions" \
    $args --seed 0 --out "$out/job$i" --name "robot_$i" > "$out/job$i.log" 2>&1 &
done
CUDA_VISIBLE_DEVICES=1 python experiments/closed_loop_select.py --policy default --n 1000 --seed 7000017 \
  --noises 0.25:0:0:0:0:0.25,0.25:0:5:3:0.5:0.25 --observe camera --warmups 20,40 --stops 0.8 \
  --out "$out/select" --name default_warmup > "$out/select.log" 2>&1 &
wait
