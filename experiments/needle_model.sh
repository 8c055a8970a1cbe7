#!/usr/bin/env bash
# Issue 30: what the 56-chord needle model changes, on one GPU machine. Stages (default: all):
#   timings     bench_env and the batched / single-query planning times (nothing else running)
#   robustness  the robustness table of every shipped policy, in parts side by side (one process
#               each, the GPU shared), joined with --merge (experiments/results/robustness/)
#   shipped     every shipped policy bare and shielded on paper300 and held-out 3000 (seed 2022),
#               and the general policies on general1000
#   bash experiments/needle_model.sh OUT [STAGE...]
set -uo pipefail
out=${1:-runs/needle_model}
shift || true
stages=${*:-timings robustness shipped}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
shipped=(decay default ensemble3 exact general general_v1 student_v1 student_v2)
if [[ " $stages " == *" timings "* ]]; then
  python experiments/bench_env.py --batch-sizes 8192,32768 --rollouts 3 --cpu-steps 300 --out "$out/env" | tail -4
  python -m regrasp_mjx.evaluate --json --batch-size 65536 --queries 300 > "$out/eval_default.json" 2> "$out/eval_default.err"
  python -m regrasp_mjx.evaluate --json --policy general --testset general1000 --batch-size 65536 --queries 300 \
    > "$out/eval_general.json" 2> "$out/eval_general.err"
fi
if [[ " $stages " == *" robustness "* ]]; then
  noise="exact,sigma 0.1 mm,sigma 0.25 mm,sigma 0.5 mm,bias 0.25 mm + sigma 0.25 mm"
  margins="margin 0.1 mm,margin 0.2 mm"
  parts=()
  for p in default exact; do  # all four modes, every row
    python experiments/robustness.py --policy "$p=$p" --out "$out/rob" --name "$p" > "$out/rob_$p.log" 2>&1 &
    parts+=("$out/rob/$p.json")
  done
  for p in decay ensemble3 general general_v1 student_v1 student_v2; do  # open and fused at the noise rows, open at the margins
    python experiments/robustness.py --policy "$p=$p" --modes open,fused --conditions "$noise" \
      --out "$out/rob" --name "${p}_noise" > "$out/rob_${p}_noise.log" 2>&1 &
    python experiments/robustness.py --policy "$p=$p" --modes open --conditions "$margins" \
      --out "$out/rob" --name "${p}_margin" > "$out/rob_${p}_margin.log" 2>&1 &
    parts+=("$out/rob/${p}_noise.json" "$out/rob/${p}_margin.json")
  done
  wait
  python experiments/robustness.py --merge "${parts[@]}" --out "$out/rob" --name robustness
fi
if [[ " $stages " == *" shipped "* ]]; then
  for p in "${shipped[@]}"; do
    python experiments/policies.py --policy "$p=$p" --out "$out/shipped" --name "$p" > "$out/shipped_$p.log" 2>&1 &
  done
  for p in general general_v1; do
    for s in "" --no-shield; do
      python -m regrasp_mjx.evaluate --json --policy $p --testset general1000 --queries 0 --repeats 0 $s \
        > "$out/general1000_${p}${s:+_bare}.json" 2> /dev/null &
    done
  done
  wait
fi
