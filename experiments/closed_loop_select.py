"""Chooses the closed loop's settings (warm-up frames, stop tolerance) on validation problems of
their own seed, never on paper300: the closed loop of a policy (default: the shipped one) at frame
noise 0.1, 0.25 and 0.5 mm (and any ``SIGMA:BIAS`` pairs of ``--noises``; ``SIGMA:BIAS:T:R:J:TOOL``
adds the robot's errors, :class:`~regrasp_mjx.robot.robot_errors.RobotErrors`, seen as ``--observe`` says);
the setting with the best mean success over them is ``Policy.execute``'s default.

    python experiments/closed_loop_select.py --n 1000 --seed 7000017 --out experiments/results/closed_loop
    python experiments/closed_loop_select.py --policy runs/x/policy --noises 0.1,0.25,0.5,0.25:0.25 --frames each
    python experiments/closed_loop_select.py --policy runs/x/policy --noises 0.25:0:0:0:0:0.25,0.25:0:5:3:0.5:0.25 \
        --observe camera --warmups 10,20 --stops 0.7,0.8
"""

from __future__ import annotations

import argparse

from regrasp_mjx.core.atomic import dumps, write_results
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.selection import closed_loop_markdown, closed_loop_settings, parse_noises
from regrasp_mjx.robot.robot_errors import OBSERVE
from regrasp_mjx.world.testsets import make_testset


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1000)
    p.add_argument("--seed", type=int, default=7000017)
    p.add_argument(
        "--noises",
        default="0.1,0.25,0.5",
        help="frame noise SIGMA, SIGMA:BIAS or SIGMA:BIAS:T:R:J:TOOL (mm, deg), comma-separated",
    )
    p.add_argument("--observe", default="camera", choices=OBSERVE, help="how the policy sees its tools")
    p.add_argument("--policy", default=None, help="policy folder or shipped name (default: the shipped one)")
    p.add_argument("--frames", default="fused", choices=("fused", "each"), help="fused frames, or each frame alone")
    p.add_argument("--name", default="select")
    p.add_argument("--warmups", default="1,5,10")
    p.add_argument("--stops", default="1,0.7,0.5")
    p.add_argument("--looks", default="0", help="frames held still to look before the last moves, comma-separated")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    policy = load_policy(args.policy)
    episodes = make_testset(args.n, args.seed, policy.env_config)  # a general policy's draws its needles too
    noises = parse_noises(args.noises)
    rows, best = closed_loop_settings(
        policy,
        episodes,
        noises,
        [int(w) for w in args.warmups.split(",")],
        [float(s) for s in args.stops.split(",")],
        frames=args.frames,
        observe=args.observe,
        log=lambda row: print(dumps(row), flush=True),
        looks=[int(x) for x in args.looks.split(",")],
    )
    lines = [
        f"Closed loop ({args.frames} frames, tools seen: {args.observe}), policy {args.policy or 'shipped'}, "
        f"{args.n} validation problems (seed "
        f"{args.seed}); success at frame noise sigma (mm) and bias (mm).",
        "",
        *closed_loop_markdown(rows, best, noises),
    ]
    print("\n".join(lines))
    write_results(
        args.out,
        args.name,
        lines,
        {
            "policy": args.policy,
            "frames": args.frames,
            "observe": args.observe,
            "noises": args.noises,
            "rows": rows,
            "best": best,
        },
    )


if __name__ == "__main__":
    main()
