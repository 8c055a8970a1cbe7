"""Success as the needle-pose estimate gets noisier, with and without projection onto the library of
valid grasps (the paper's real-world failure, §V-C).

For each test problem the policy plans from an observed needle pose, the true one moved by
Gaussian noise (``sigma`` mm on each axis, ``5 * sigma`` degrees about a random axis per mm, i.e.
the success test's 1 mm : 5 degree scale); the goal grasp is the same grasp on the observed needle.
The planned actions are then executed against the true needle (collisions and success judged
there). With projection, the observed pose is first replaced by the nearest library pose.

    python experiments/needle_noise.py --sigmas 0,0.25,0.5,1,2 --out experiments/results
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from results_io import write_results

from regrasp_mjx import host
from regrasp_mjx.env import RegraspEnv
from regrasp_mjx.grasps import GraspLibrary
from regrasp_mjx.planning.episodes import make_replay
from regrasp_mjx.policy import load_policy
from regrasp_mjx.sampling import load_testset
from regrasp_mjx.train import DEFAULT_TESTSET


def perturb(needle: np.ndarray, sigma_mm: float, rng: np.random.Generator) -> np.ndarray:
    out = needle.copy()
    out[:, :3] += rng.normal(0.0, sigma_mm * 1e-3, (len(needle), 3))
    axis = rng.normal(size=(len(needle), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(rng.normal(0.0, 5.0 * sigma_mm, len(needle)))
    for i in range(len(needle)):
        out[i, 3:] = host.canonical(host.quat_mul(host.quat_from_rotvec(axis[i] * angle[i]), needle[i, 3:]))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sigmas", default="0,0.25,0.5,1,2")
    p.add_argument("--policy", default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    policy = load_policy(args.policy)
    env = RegraspEnv(policy.env_config)
    replay = make_replay(env)
    lib = GraspLibrary.default()
    ep, _ = load_testset(DEFAULT_TESTSET)
    needle = np.c_[ep.needle_pos, ep.needle_quat]
    start = np.c_[ep.start_pos, ep.start_quat]
    goal = np.c_[ep.goal_pos, ep.goal_quat]
    goal_in_needle = [host.relative(n[:3], n[3:], g[:3], g[3:]) for n, g in zip(needle, goal)]
    truth = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), ep)
    rng = np.random.default_rng(args.seed)
    rows = []
    for sigma in (float(s) for s in args.sigmas.split(",")):
        observed = perturb(needle, sigma, rng)
        for project in (False, True):
            seen = lib.project(observed) if project else observed
            seen_goal = np.stack([_compose(s, g) for s, g in zip(seen, goal_in_needle)])
            plan = policy.plan(seen, start, seen_goal, check_grasp=False)
            out = jax.device_get(replay(truth, jnp.asarray(plan.actions, jnp.float32)))
            done = out["done"] > 0
            first = np.where(done.any(1), np.argmax(done, 1), -1)
            ok = (first >= 0) & (out["success"][np.arange(len(first)), np.clip(first, 0, None)] > 0)
            # only the planned steps count: past a plan's end the replay runs zero actions
            ok &= first <= plan.steps - 1
            rows.append(
                {
                    "sigma_mm": sigma,
                    "sigma_deg": 5 * sigma,
                    "projection": project,
                    "success_true": float(ok.mean()),
                    "success_planned": float(plan.success.mean()),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    lines = [
        "| needle noise (mm, deg) | projection | success on the true needle | success as planned |",
        "| --- | --- | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['sigma_mm']}, {r['sigma_deg']} | {'yes' if r['projection'] else 'no'} | "
            f"{r['success_true']:.3f} | {r['success_planned']:.3f} |"
        )
    print("\n".join(lines))
    write_results(args.out, "needle_noise", lines, rows)


def _compose(a: np.ndarray, b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    import mujoco

    pos, quat = np.empty(3), np.empty(4)
    mujoco.mju_mulPose(pos, quat, a[:3], a[3:], b[0], b[1])
    return np.r_[pos, host.canonical(quat)]


if __name__ == "__main__":
    main()
