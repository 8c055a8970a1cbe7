#!/usr/bin/env bash
# Issue 68's GPU session (2026-11-29, second): frames whose regrasping jaws open on the way, the estimator
# trained on them, its held-out errors and the camera-error model fitted to them, its time per stereo pair,
# then the shipped default from pixels on paper300 and on 300 held-out problems, each loop in SHARDS
# processes side by side (the renderer draws one picture at a time; a GPU host's cores go further so).
# One H200 host (16 cores), MUJOCO_GL=egl, the package importable. Each step resumes, or is skipped when
# its output exists: run it again after a time limit.
#
#   MUJOCO_GL=egl bash experiments/pixels_gpu.sh OUT
set -euo pipefail
out=${1:?"usage: pixels_gpu.sh OUT"}
workers=${WORKERS:-14}
shards=${SHARDS:-10}  # 300 problems in batches of 32: one batch a shard
# smaller, to try the script on a CPU: EPISODES="8 4 4" EPOCHS=1 LOOP_N=4 bash experiments/pixels_gpu.sh /tmp/try
read -r n_train n_val n_test <<<"${EPISODES:-2000 100 250}"
epochs=${EPOCHS:-30}
only=(${LOOP_N:+--n "$LOOP_N"})
jaws=(--jaw-open 25 60)  # the shipped default opens them to 40; the LND to 80
e() {
    echo "== $(date +%T) estimator $1" >&2 # stderr: a command's stdout may be a result file
    python -m regrasp_mjx.estimator "$@"
}
mkdir -p "$out"
for s in "train $n_train 0" "val $n_val 1" "test $n_test 2"; do
    read -r name episodes seed <<<"$s"
    [ -f "$out/$name.npz" ] || e render --out "$out/$name.npz" --episodes "$episodes" --frames 8 --seed "$seed" \
        --workers "$workers" "${jaws[@]}"
done
[ -f "$out/est/estimator/estimator.json" ] && [ -f "$out/est/done" ] || {
    e train --data "$out/train.npz" --val "$out/val.npz" --out "$out/est" --epochs "$epochs"
    touch "$out/est/done"
}
[ -f "$out/eval/estimator_errors.json" ] || e evaluate --estimator "$out/est/estimator" --data "$out/test.npz" --out "$out/eval"
[ -f "$out/camera_rendered.json" ] || e fit --errors "$out/eval" --out "$out/camera_rendered.json"
[ -s "$out/bench_one_pair.json" ] || e bench --estimator "$out/est/estimator" --repeats 200 >"$out/bench_one_pair.json"
[ -s "$out/bench_batch64.json" ] || e bench --estimator "$out/est/estimator" --repeats 50 --batch 64 >"$out/bench_batch64.json"
# the loops: XLA takes GPU memory as it needs it (SHARDS processes share one GPU)
export XLA_PYTHON_CLIENT_PREALLOCATE=false
loop() {
    local name=$1
    shift
    local common=(--estimator "$out/est/estimator" --policy default --seed 3 --camera "$out/camera_rendered.json" "${only[@]}")
    [ -f "$out/$name/pixel_loop.json" ] && return 0
    local pids=() i
    for i in $(seq 0 $((shards - 1))); do
        e loop "${common[@]}" "$@" --out "$out/$name" --shard "$i/$shards" >>"$out/$name.shard$i.log" 2>&1 &
        pids+=($!)
    done
    for i in "${!pids[@]}"; do  # a failed shard is said; the report's run runs the batches it left
        wait "${pids[$i]}" || echo "== shard $i of $shards failed (exit $?): $out/$name.shard$i.log" >&2
    done
    e loop "${common[@]}" "$@" --out "$out/$name"
}
loop paper300 --testset paper300
loop heldout300 --heldout 300:2022
echo "== $(date +%T) done"
