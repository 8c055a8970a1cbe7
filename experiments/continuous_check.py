"""Every plan reported collision-free re-posed densely along its whole motion (issue 44).

Each step of each plan that ended in success (or a time-out: also reported free) is re-posed at
``--poses`` poses (s = k / poses, k = 0..poses, as the environment moves: position linear,
orientation along the rotation vector), and every counted pair's signed distance is taken with the
environment's capsule model (``Scene.distance_fn``, around each problem's own needle). The model's
needle capsules hold the true wire (``Scene.needle_error_bound``; tests/test_clearance.py), so a pose
clear in the model is clear of the true wire and of the other tool. Reported per policy, test set
and shield setting: plans, steps and poses re-checked, the poses below 0 (penetrations; must be 0),
and the smallest clearance found [um].

    python experiments/continuous_check.py --policies default,general --out experiments/results/continuous
    python experiments/continuous_check.py --closed-loop-noise-mm 0.25 --out experiments/results/continuous

With ``--closed-loop-noise-mm``, each policy's fused closed loop (its own settings, seed 0) runs under
that needle-pose noise instead, and every executed motion that did not collide is re-posed against
the true needle.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from regrasp_mjx.core import geometry as g
from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.inference.closed_loop_host import execute
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world.sampling import episode_needles, episode_poses, load_testset
from regrasp_mjx.world.scene import load_scene


def recheck(policy, testset: str, shield: bool, poses: int, limit: int | None, noise_mm: float | None = None) -> dict:
    """``noise_mm`` None: the policy's plans (``Policy.plan``); else its fused closed loop under that
    needle-pose noise (seed 0, its own closed-loop settings), the executed true poses re-checked
    against the true needle."""
    episodes, _ = load_testset(testset)
    needle, start, goal = episode_poses(episodes)
    n = len(needle) if limit is None else min(limit, len(needle))
    varies = policy.env_config.task.varies_needle
    radii = episode_needles(episodes) if varies else {}
    task = {k: v[:n] for k, v in radii.items()}
    if noise_mm is None:
        plan = policy.plan(needle[:n], start[:n], goal[:n], shield=shield, check_grasp=False, engine="jax", **task)
        # a time-out is reported free too
        free, success, steps, trajectories = plan.success | plan.time_out, plan.success, plan.steps, plan.poses
    else:
        out = execute(policy, needle[:n], start[:n], goal[:n], NeedleNoise(sigma_mm=noise_mm), shield=shield, **task)
        # every executed motion that did not collide (a success, a time-out or a stop short of the goal)
        free, success, steps, trajectories = (
            out["start_valid"] & ~out["collision"],
            out["success"],
            out["steps"],
            out["poses"],
        )
    free, success = np.asarray(free), np.asarray(success)
    scene = load_scene(policy.env_config.scene)
    distances = scene.distance_fn()
    s = jnp.arange(poses + 1, dtype=jnp.float32) / poses

    @jax.jit
    def step_min(nd, a, b, needle_r, wire_r):
        dp = b[:3] - a[:3]
        w = (jaxlie.SO3(g.canonical_quat(g.quat_mul(b[3:], jaxlie.SO3(a[3:]).inverse().wxyz)))).log()
        pos = a[:3] + s[:, None] * dp
        quat = g.quat_mul(g.quat_from_rotvec(s[:, None] * w), a[3:])
        extra = (needle_r, wire_r) if varies else ()
        d = jax.vmap(lambda p, q: jnp.min(distances(nd[:3], nd[3:], p, q, *extra)))(pos, quat)
        return jnp.min(d)

    worst, below, total = np.inf, 0, 0
    for i in np.flatnonzero(free):
        k = int(steps[i])
        traj = jnp.asarray(trajectories[i][: k + 1])
        nd = jnp.asarray(needle[i], jnp.float32)
        nr = jnp.float32(radii["needle_radius_mm"][i] * 1e-3) if varies else jnp.float32(0)
        wr = jnp.float32(radii["wire_radius_mm"][i] * 1e-3) if varies else jnp.float32(0)
        mins = np.asarray(jax.vmap(step_min, in_axes=(None, 0, 0, None, None))(nd, traj[:-1], traj[1:], nr, wr))
        worst = min(worst, float(mins.min()) if len(mins) else worst)
        below += int((mins < 0.0).sum())
        total += k
    return {
        "plans": int(n),
        "free_plans": int(free.sum()),
        "success": round(float(success[:n].mean()), 4),
        "steps_rechecked": total,
        "poses_per_step": poses + 1,
        "steps_below_zero": below,
        "smallest_clearance_um": None if not np.isfinite(worst) else round(worst * 1e6, 3),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policies", default="default")
    p.add_argument("--poses", type=int, default=1000, help="poses per step (>= 1000 for the issue's check)")
    p.add_argument("--limit", type=int, default=None, help="first N problems of each test set")
    p.add_argument(
        "--closed-loop-noise-mm",
        type=float,
        default=None,
        help="instead of plans, each policy's fused closed loop under this needle-pose noise (sigma, mm; seed 0)",
    )
    p.add_argument("--out", default=None)
    args = p.parse_args()
    sigma = args.closed_loop_noise_mm
    what = "plans" if sigma is None else f"fused closed loop, sigma {sigma:g} mm"
    rows = []
    for name in args.policies.split(","):
        policy = load_policy(name)
        testset = "general1000" if policy.env_config.task.general else "paper300"
        for shield in (False, True):
            row = {"policy": name, "testset": testset, "shield": shield, "what": what}
            row.update(recheck(policy, testset, shield, args.poses, args.limit, sigma))
            print(row, flush=True)
            rows.append(row)
    head = "| policy | what | test set | shield | success | plans re-checked | steps | poses a step | steps below 0 | smallest clearance (um) |"
    lines = [f"Machine: {machine()}", "", head, "|" + " --- |" * 10]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['what']} | {r['testset']} | {'on' if r['shield'] else 'off'} | {r['success']:.3f} | "
            f"{r['free_plans']} | {r['steps_rechecked']} | {r['poses_per_step']} | {r['steps_below_zero']} | "
            f"{r['smallest_clearance_um']} |"
        )
    print("\n".join(lines))
    if args.out:
        name = "continuous_check" if sigma is None else f"continuous_check_closed_loop_{sigma:g}mm"
        write_results(args.out, name, lines, {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
