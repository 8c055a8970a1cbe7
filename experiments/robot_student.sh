#!/usr/bin/env bash
# Students that see their tools through the camera (issue 45), and the closed loop's settings chosen
# for each on validation problems of their own seed (never paper300), all on one machine's GPUs:
#   bash experiments/robot_student.sh OUT_DIR
# Students: DAgger from the shipped default (teacher labels true states) acting on a noisy needle
# (U[0, 0.5] mm, bias U[0, 0.25] mm) and noisy tools (U[0, TOOL] mm), two seeds at TOOL 0.5, one at 0.75.
# Selection: fused closed loop, tools seen by the camera, sigma = sigma_tool = 0.25 mm, without and
# with a 5 mm / 3 deg calibration error and 0.5 joint offsets; 1000 problems of seed 7000017.
set -euo pipefail
out=${1:?usage: robot_student.sh OUT_DIR}
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
gpus=$(python -c "import jax; print(jax.device_count())")
recipe=(--teacher default --set "hidden=(256,256)" --set iterations=20 --set obs_noise_mm=0.5
        --set obs_bias_mm=0.25 --set goal_tolerance=0.7)
students=("t05s1 1 0.5" "t05s2 2 0.5" "t075s1 1 0.75")
i=0
for s in "${students[@]}"; do
  read -r name seed tool <<< "$s"
  CUDA_VISIBLE_DEVICES=$((i % gpus)) python -m regrasp_mjx.distill "${recipe[@]}" --seed "$seed" \
    --set obs_tool_noise_mm="$tool" --out "$out/$name" > "$out/$name.log" 2>&1 &
  i=$((i + 1))
done
wait
i=0
for name in default t05s1 t05s2 t075s1; do
  policy=$out/$name/policy; [ "$name" = default ] && policy=default
  CUDA_VISIBLE_DEVICES=$((i % gpus)) python experiments/closed_loop_select.py --policy "$policy" --n 1000 \
    --seed 7000017 --noises 0.25:0:0:0:0:0.25,0.25:0:5:3:0.5:0.25 --observe camera --warmups 10,20 \
    --stops 0.7,0.8 --out "$out/select" --name "$name" > "$out/select_$name.log" 2>&1 &
  i=$((i + 1))
done
wait
