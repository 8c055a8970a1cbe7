"""One closed-loop step on one CPU core: ``Policy.closed_loop_step`` (the lean numba step, the default
for one query on the CPU), the same step through the JAX program, and ``CameraLoop.update`` (a camera
frame of both tools and the needle: fusing, the step, the tool-frame motion).

The states are every pose along the policy's plans (``--policy``, default the shipped default) of the
first ``--queries`` paper300 problems (the start, each step, the goal), visited in rounds; each round
rotates which method goes first. A policy whose jaws open on the way steps each state with its jaws
where its plan has them there (``jaw_opening.opening_steps``) and has no ``CameraLoop`` row (the
camera loop carries the opening since 2026-11-29, but this benchmark does not feed it one yet). Prints each method's median, mean and 90th percentile in
milliseconds.

    python experiments/bench_closed_loop.py --core 0 --out experiments/results/robot_errors
"""

from __future__ import annotations

import argparse
import os

if __name__ == "__main__":  # one core, before JAX starts its thread pools
    _core = argparse.ArgumentParser(add_help=False)
    _core.add_argument("--core", type=int, default=0)
    os.sched_setaffinity(0, {_core.parse_known_args()[0].core})
    os.environ.setdefault("JAX_PLATFORMS", "cpu")

import time
from datetime import date

import numpy as np

from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.inference.jaw_opening import opening_steps
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.robustness import policy_hash
from regrasp_mjx.robot import dvrk
from regrasp_mjx.world.sampling import episode_poses, load_testset


def _vec(m):
    w = np.sqrt(1.0 + np.trace(m[:3, :3])) / 2.0
    r = m[:3, :3]
    return np.r_[
        m[:3, 3], w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--core", type=int, default=0, help="the CPU core this process is pinned to (default 0)")
    p.add_argument("--policy", default=None, help="a shipped name or policy folder (default: the shipped default)")
    p.add_argument("--queries", type=int, default=50, help="paper300 problems whose plans give the states")
    p.add_argument("--repeats", type=int, default=5, help="rounds over all states and methods")
    p.add_argument("--out", default=None, help="folder for bench_closed_loop.md and .json")
    args = p.parse_args()
    policy = load_policy(args.policy)
    episodes, _ = load_testset("paper300")
    needle, start, goal = (x[: args.queries] for x in episode_poses(episodes))
    plan = policy.plan(needle, start, goal, check_grasp=False, engine="jax")
    queries = range(len(needle))
    base, wide = policy.env_config.scene.jaw_angle_deg, policy.env_config.jaw_open_deg
    jaws = {}  # the jaws' opening at each state, for a policy that opens them on the way
    if wide is not None:
        opened = opening_steps(policy, needle, plan.poses, plan.steps)
        jaws = {
            (i, k): {"jaw_deg": wide if 0 <= opened[i] < k else base} for i in queries for k in range(plan.steps[i] + 1)
        }
    states = [
        (needle[i], plan.poses[i, k], goal[i], k, jaws.get((i, k), {}))
        for i in queries
        for k in range(plan.steps[i] + 1)
    ]
    camera = dvrk.pose_matrix(np.array([0.03, -0.02, 0.1, 0.3, 0.8, -0.1, 0.5]))
    cam_inv = np.linalg.inv(camera)
    frames = [
        [_vec(cam_inv @ dvrk.pose_matrix(x)) for x in (np.r_[0, 0, 0, 1, 0, 0, 0], e, n)] for n, e, _, _, _ in states
    ]
    loop = None if wide is not None else policy.camera_loop(warmup_frames=1)  # it does not carry the jaws

    def lean(s):
        policy.closed_loop_step(s[0], s[1], s[2], t=s[3], **s[4])

    def jax_path(s):  # a batch of one: the JAX program
        policy.closed_loop_step(s[0][None], s[1][None], s[2][None], t=s[3], **s[4])

    def camera_frame(i):
        loop.update(*frames[i])

    methods = {"closed_loop_step (lean)": lean, "closed_loop_step (JAX, batch of one)": jax_path}
    for f in methods.values():  # compile and warm up
        for s in states[:3]:
            f(s)
    names = [*methods] + ([] if loop is None else ["CameraLoop.update"])
    if loop is not None:
        camera_frame(0)
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(args.repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            for i, s in enumerate(states):
                t0 = time.perf_counter()
                camera_frame(i) if name == "CameraLoop.update" else methods[name](s)
                times[name].append(time.perf_counter() - t0)
    rows = {
        name: {
            "median_ms": float(np.median(v) * 1e3),
            "mean_ms": float(np.mean(v) * 1e3),
            "p90_ms": float(np.percentile(v, 90) * 1e3),
            "calls": len(v),
        }
        for name, v in times.items()
    }
    where = machine(devices=False) + f"; pinned to core {args.core}"
    lines = [
        f"One closed-loop step, one query at a time: {where}; {date.today()}; policy {args.policy or 'default'} "
        f"(hash {policy_hash(args.policy)}); {len(states)} states along {len(needle)} paper300 plans, {args.repeats} rounds.",
        "",
        "| method | median ms | mean ms | p90 ms | calls |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {n} | {r['median_ms']:.4f} | {r['mean_ms']:.4f} | {r['p90_ms']:.4f} | {r['calls']} |"
        for n, r in rows.items()
    ]
    print("\n".join(lines))
    write_results(args.out, "bench_closed_loop", lines, {"machine": where, "date": str(date.today()), "rows": rows})


if __name__ == "__main__":
    main()
