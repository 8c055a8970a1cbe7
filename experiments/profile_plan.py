"""Where batched planning's time goes: ``Policy.plan`` on a batch, split into its parts.

For each batch size, the test set's queries are repeated up to it and planned (shielded and bare)
with the shipped policy; the script times, each the median of ``--repeats`` calls after a warm-up:
the whole ``Policy.plan`` call; the jitted program alone with its inputs already on the device
(``block_until_ready``); the copy of what it returns to the host (the planner called, less the
program: the outcome, then the trajectories cut after the longest plan); building the ``Plan``; and
what is left, the checks and conversion of the inputs. It also prints the while loop's length (the longest plan of the batch) against the mean
plan, which bounds what a loop that stops at the longest plan wastes, and plans/s.

    python experiments/profile_plan.py --batch-sizes 8192,65536 --out experiments/results/profile_plan
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from datetime import date

import jax
import numpy as np

from regrasp_mjx.core.atomic import write_results
from regrasp_mjx.inference import plans
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.queries import TaskSpec
from regrasp_mjx.world.sampling import episode_needles, episode_poses, load_testset


def median_s(fn, repeats: int) -> float:
    fn()  # warm-up (compiles on first use)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def profile(policy, episodes, batch: int, shield: bool, repeats: int) -> dict:
    needle, start, goal = episode_poses(episodes)
    needles = episode_needles(episodes)
    rows = np.arange(batch) % len(needle)
    needle, start, goal = needle[rows], start[rows], goal[rows]
    kw = {k: v[rows] for k, v in needles.items()}
    plan = lambda: policy.plan(needle, start, goal, check_grasp=False, shield=shield, **kw)  # noqa: E731
    total = median_s(plan, repeats)
    result = plan()

    planner = policy.program((False, shield))  # functools.partial(Planner, weights)
    grasp, radii = policy.task_ranges.resolve(batch, TaskSpec.of(kw))
    f32 = lambda x: jax.device_put(np.asarray(x, np.float32))  # noqa: E731
    args = (planner.args[0], f32(needle), f32(start), f32(goal), f32(radii))
    program = planner.func.program(batch)  # the one this batch runs: whole, or outcome first
    device = median_s(lambda: jax.block_until_ready(program(*args)), repeats)
    called = median_s(lambda: planner.func(*args), repeats)  # the program and the copy of what it returns
    out = planner.func(*args)
    finish = median_s(lambda: plans._finish(out, False, None), repeats)
    steps = np.asarray(result.steps)
    return {
        "batch": batch,
        "shield": shield,
        "plan_s": total,
        "program_s": device,
        "copy_s": called - device,
        "finish_s": finish,
        "inputs_s": total - called - finish,
        "copied_mb": sum(x.nbytes for x in jax.tree.leaves(out)) / 1e6,
        "loop_steps": int(steps.max()),
        "mean_steps": float(steps.mean()),
        "success": float(np.mean(result.success)),
        "plans_per_s": batch / total,
        "program_plans_per_s": batch / device,
    }


def fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:,.0f}" if v >= 100 else f"{v:.4g}"
    return str(v)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=None, help="a shipped name or policy folder (default: the shipped default)")
    p.add_argument("--testset", default="paper300", help="a shipped name or .npz (default paper300)")
    p.add_argument("--batch-sizes", default="8192,65536", help="comma-separated batch sizes")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per part (default 3)")
    p.add_argument("--out", default=None, help="folder for profile_plan.md and profile_plan.json")
    args = p.parse_args()
    try:
        batches = [int(b) for b in args.batch_sizes.split(",")]
    except ValueError:
        p.error(f"--batch-sizes {args.batch_sizes!r} is not accepted: comma-separated integers >= 1")
    if min(batches) < 1 or args.repeats < 1:
        p.error("--batch-sizes and --repeats are accepted as integers >= 1")
    policy = load_policy(args.policy)
    episodes, _ = load_testset(args.testset)
    rows = [profile(policy, episodes, b, s, args.repeats) for b in batches for s in (True, False)]
    machine = f"{jax.default_backend()}: {jax.devices()[0].device_kind}; {platform.node()}, {os.cpu_count()} cores"
    cols = ["batch", "shield", "plan_s", "program_s", "copy_s", "finish_s", "inputs_s"]
    cols += ["copied_mb", "loop_steps", "mean_steps", "success", "plans_per_s", "program_plans_per_s"]
    lines = [
        f"Machine: {machine}; jax {jax.__version__}; {date.today()}; policy {args.policy or 'default'}, {args.testset}",
        "",
    ]
    lines += ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in rows]
    text = "\n".join(lines)
    print(text)
    if args.out:
        write_results(args.out, "profile_plan", lines, {"machine": machine, "rows": rows})


if __name__ == "__main__":
    main()
