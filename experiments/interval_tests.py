"""How many interval tests the continuous collision test takes a step: the motion bound alone (the
test before the directional bound) against both bounds (``continuous.interval_low``), on the same
steps, with the host checker (float64, CPU MuJoCo's distances).

Steps: every step of the shipped default's plans on paper300 (bare and shielded), and random
actions from paper300's starts (``--walks`` rows, up to ``--steps`` steps each, a walk ends at its
first collision). Per step set: steps, the share whose root interval is not proved (pending: they
walk halves), the mean and largest tests, steps needing more than 8, and the verdicts that differ
(only steps the motion bound could not prove within the budget may change: both bounds prove at
least what the motion bound proves, and neither proves a pose that collides).

    python experiments/interval_tests.py --out experiments/results/continuous
"""

from __future__ import annotations

import argparse
import math
from contextlib import contextmanager

import numpy as np

from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.envs.host import HostChecker, quat_conj, quat_from_rotvec, quat_mul, quat_to_rotvec
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world import continuous
from regrasp_mjx.world.sampling import episode_poses, load_testset

BOUNDS = ("motion", "both")


@contextmanager
def counted(bound: str, tally: list[int]):
    """The host walk with its interval tests counted into ``tally`` (one entry a step) and, for
    ``bound="motion"``, :func:`continuous.interval_low` reduced to the motion bound."""
    walk, low = continuous.motion_collides_host, continuous.interval_low

    def motion_only(tool, origin, other, gap, d, h, dp, rotvec, levers, xp):
        return d - h * (xp.linalg.norm(dp) + xp.linalg.norm(rotvec) * levers)[:, None]

    def counting(bound_at, fastest, margin):
        tally.append(0)

        def at(*args):
            tally[-1] += 1
            return bound_at(*args)

        return walk(at, fastest, margin)

    continuous.motion_collides_host = counting
    if bound == "motion":
        continuous.interval_low = motion_only
    try:
        yield
    finally:
        continuous.motion_collides_host, continuous.interval_low = walk, low


def plan_steps(needle, start, goal, shield: bool) -> list[tuple]:
    """``(needle, pose, dp, rotvec)`` of every step of the default's plans."""
    plan = load_policy("default").plan(needle, start, goal, shield=shield, check_grasp=False, engine="jax")
    steps = []
    for i in range(len(needle)):
        poses = np.asarray(plan.trajectory(query=i), np.float64)
        for a, b in zip(poses[:-1], poses[1:]):
            q = a[3:] / np.linalg.norm(a[3:])
            steps.append((needle[i], a[:3], q, b[:3] - a[:3], quat_to_rotvec(quat_mul(b[3:], quat_conj(q)))))
    return steps


def random_steps(checker: HostChecker, needle, start, walks: int, length: int, seed: int) -> list[tuple]:
    """Random full-range actions from the first ``walks`` starts, each walk to its first collision."""
    rng = np.random.default_rng(seed)
    max_dp, max_drot = 0.5e-3, math.radians(3.0)
    steps = []
    for i in range(min(walks, len(needle))):
        p, q = start[i, :3].astype(np.float64), start[i, 3:] / np.linalg.norm(start[i, 3:])
        for _ in range(length):
            a = rng.uniform(-1.0, 1.0, 6)
            dp, w = a[:3] * max_dp, a[3:] * max_drot
            steps.append((needle[i], p, q, dp, w))
            if checker.motion_collides(needle[i, :3], needle[i, 3:], p, q, dp, w):
                break
            p, q = p + dp, quat_mul(quat_from_rotvec(w), q)
    return steps


def measure(checker: HostChecker, steps: list[tuple]) -> dict:
    """Both bounds' tests and verdicts on ``steps``."""
    out = {}
    for bound in BOUNDS:
        tally: list[int] = []
        with counted(bound, tally):
            verdicts = [checker.motion_collides(n[:3], n[3:], p, q, dp, w) for n, p, q, dp, w in steps]
        out[bound] = (np.array(tally), np.array(verdicts))
    tests = {b: out[b][0] for b in BOUNDS}
    row = {"steps": len(steps), "verdicts_differ": int(np.sum(out["motion"][1] != out["both"][1]))}
    for b in BOUNDS:
        row[b] = {
            "pending_share": round(float(np.mean(tests[b] > 1)), 4),
            "mean_tests": round(float(tests[b].mean()), 3),
            "max_tests": int(tests[b].max()),
            "over_8": int(np.sum(tests[b] > 8)),
            "collisions": int(out[b][1].sum()),
        }
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--walks", type=int, default=100, help="paper300 starts the random walks begin at")
    p.add_argument("--steps", type=int, default=40, help="the most steps a random walk takes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    episodes, _ = load_testset("paper300")
    needle, start, goal = episode_poses(episodes)
    checker = HostChecker()
    sets = {
        "default on paper300, bare": plan_steps(needle, start, goal, shield=False),
        "default on paper300, shielded": plan_steps(needle, start, goal, shield=True),
        f"random actions, {args.walks} walks (seed {args.seed})": random_steps(
            checker, needle, start, args.walks, args.steps, args.seed
        ),
    }
    rows = []
    for name, steps in sets.items():
        row = {"steps_of": name, **measure(checker, steps)}
        print(row, flush=True)
        rows.append(row)
    head = "| steps of | steps | pending (motion / both) | mean tests | largest | > 8 tests | collisions | verdicts differ |"
    lines = [f"Machine: {machine(devices=False)}", "", head, "|" + " --- |" * 8]
    for r in rows:
        m, b = r["motion"], r["both"]
        lines.append(
            f"| {r['steps_of']} | {r['steps']} | {m['pending_share']:.3f} / {b['pending_share']:.3f} | "
            f"{m['mean_tests']:.2f} / {b['mean_tests']:.2f} | {m['max_tests']} / {b['max_tests']} | "
            f"{m['over_8']} / {b['over_8']} | {m['collisions']} / {b['collisions']} | {r['verdicts_differ']} |"
        )
    print("\n".join(lines))
    write_results(args.out, "interval_tests", lines, {"machine": machine(devices=False), "rows": rows})


if __name__ == "__main__":
    main()
