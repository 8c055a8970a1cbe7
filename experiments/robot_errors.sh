#!/usr/bin/env bash
# The robot-error rows of the robustness table (issue 45) for every shipped policy, and the default's on
# held-out problems, as parallel jobs over the GPUs of one machine (up to three per GPU):
#   bash experiments/robot_errors.sh OUT_DIR
# then: python -m regrasp_mjx.compare --robustness --merge OUT_DIR/*/robot_*.json ... (experiments/RESULTS.md)
set -euo pipefail
out=${1:?usage: robot_errors.sh OUT_DIR}
conditions=$(python -c "from regrasp_mjx import robustness; print(','.join(c.name for c in robustness.ROBOT_CONDITIONS))")
gpus=$(python -c "import jax; print(jax.device_count())")
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.3 PYTHONUNBUFFERED=1
jobs=(
  "--policy default --policy exact"
  "--policy decay --policy ensemble3"
  "--policy general --policy general_v1"
  "--policy student_v1 --policy student_v2"
  "--policy default --heldout 3000:2022 --no-testset"
)
for i in "${!jobs[@]}"; do
  CUDA_VISIBLE_DEVICES=$((i % gpus)) python -m regrasp_mjx.compare --robustness --conditions "$conditions" \
    ${jobs[$i]} --seed 0 --out "$out/job$i" --name "robot_$i" > "$out/job$i.log" 2>&1 &
done
wait
