"""Success as the needle-pose estimate gets noisier: planning once (open loop) against re-planning
every step from the latest or the fused estimate (closed loop), with and without a fixed bias.

Noise model (``regrasp_mjx.estimates.NeedleNoise``): each camera frame's estimate is the true
needle moved by Gaussian noise, ``sigma`` mm per axis and ``5 sigma`` degrees about a random axis,
after a bias fixed for the episode (a shift of ``bias`` mm in a random direction, ``5 bias`` degrees
about a random axis). Success and collisions are judged on the true needle.

- ``open``: one frame, one plan (``Policy.plan`` with the goal grasp on the estimate), its actions
  executed against the true needle (``projection``: the estimate first replaced by the nearest pose
  of the valid-grasp library).
- ``closed``: ``Policy.execute`` with ``frames="each", warmup_frames=1, stop_tolerance=1``: each step
  the policy acts on that step's frame and stops when that frame says the goal is reached.
- ``closed, fused``: ``Policy.execute`` with its defaults: the frames so far averaged, 10 frames
  before the first step, stop when the fused estimate is within 0.7 of the success tolerances.

    python experiments/needle_noise.py --sigmas 0,0.1,0.25,0.5,1 --biases 0,0.25,0.5 --out experiments/results
    python experiments/needle_noise.py --closed-loop --sigmas 0.25 --json   # closed loop only, JSON lines
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx import host  # noqa: E402
from regrasp_mjx.atomic import write_results  # noqa: E402
from regrasp_mjx.env import RegraspEnv  # noqa: E402
from regrasp_mjx.estimates import NeedleNoise, episode_bias, frame_estimate  # noqa: E402
from regrasp_mjx.evaluate import DEFAULT_TESTSET, episode_poses  # noqa: E402
from regrasp_mjx.grasps import GraspLibrary  # noqa: E402
from regrasp_mjx.planning.episodes import make_replay, replayed  # noqa: E402
from regrasp_mjx.policy import load_policy  # noqa: E402
from regrasp_mjx.sampling import load_testset  # noqa: E402

MODES = ("open", "open, projection", "closed", "closed, fused")


def open_loop(policy, replay, lib, truth, needle, start, grasp, estimate, project: bool) -> float:
    seen = lib.project(estimate) if project else estimate
    seen_goal = np.stack([_compose(s, g) for s, g in zip(seen, grasp)])
    plan = policy.plan(seen, start, seen_goal, check_grasp=False)
    out = jax.device_get(replay(truth, jnp.asarray(plan.actions, jnp.float32)))
    return float(replayed(out, plan.steps).mean())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sigmas", default="0,0.1,0.25,0.5,1", help="per-frame noise, mm (comma-separated)")
    p.add_argument("--biases", default="0", help="fixed per-episode bias, mm (comma-separated)")
    p.add_argument("--closed-loop", action="store_true", help="only the closed-loop rows")
    p.add_argument("--policy", default=None)
    p.add_argument("--testset", default=str(DEFAULT_TESTSET))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print only one JSON line per setting")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    policy = load_policy(args.policy)
    episodes, _ = load_testset(args.testset)
    needle, start, goal = episode_poses(episodes)
    grasp = [host.relative(n[:3], n[3:], g[:3], g[3:]) for n, g in zip(needle, goal)]
    modes = MODES[2:] if args.closed_loop else MODES
    if not args.closed_loop:
        replay, lib = make_replay(RegraspEnv(policy.env_config)), GraspLibrary.default()
        truth = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), episodes)
    rows = []
    for bias in (float(b) for b in args.biases.split(",")):
        for sigma in (float(s) for s in args.sigmas.split(",")):
            key = jax.random.PRNGKey(args.seed)
            one_frame = np.asarray(
                frame_estimate(key, episode_bias(jax.random.fold_in(key, 1), jnp.asarray(needle), bias), sigma),
                np.float64,
            )
            for mode in modes:
                if mode.startswith("open"):
                    success = open_loop(
                        policy, replay, lib, truth, needle, start, grasp, one_frame, "projection" in mode
                    )
                    collision = None
                else:
                    kwargs = (
                        {} if mode == "closed, fused" else {"frames": "each", "warmup_frames": 1, "stop_tolerance": 1.0}
                    )
                    r = policy.execute(needle, start, goal, NeedleNoise(sigma, bias), seed=args.seed, **kwargs)
                    success, collision = float(r["success"].mean()), float(r["collision"].mean())
                row = {
                    "sigma_mm": sigma,
                    "bias_mm": bias,
                    "mode": mode,
                    "closed_loop": mode.startswith("closed"),
                    "fused": mode == "closed, fused",
                    "success_rate": success,
                    "collision_rate": collision,
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        return
    lines = [
        "Success on the true needle, paper300, shipped policy (shielded). Rows: per-frame noise sigma (mm; "
        "rotation 5 sigma degrees) and a fixed bias (mm; 5 bias degrees).",
        "",
        "| sigma (mm) | bias (mm) | " + " | ".join(modes) + " |",
        "| ---: | ---: |" + " ---: |" * len(modes),
    ]
    for bias in sorted({r["bias_mm"] for r in rows}):
        for sigma in sorted({r["sigma_mm"] for r in rows}):
            cells = [r for r in rows if r["sigma_mm"] == sigma and r["bias_mm"] == bias]
            lines.append(f"| {sigma:g} | {bias:g} | " + " | ".join(f"{r['success_rate']:.3f}" for r in cells) + " |")
    print("\n".join(lines))
    write_results(args.out, "needle_noise", lines, rows)


def _compose(a: np.ndarray, b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    import mujoco

    pos, quat = np.empty(3), np.empty(4)
    mujoco.mju_mulPose(pos, quat, a[:3], a[3:], b[0], b[1])
    return np.r_[pos, host.canonical(quat)]


if __name__ == "__main__":
    main()
