"""A policy under a real camera's errors (issue 67): the closed loop's look budget and stop tolerance
chosen on validation problems of their own seed, then the policy's own settings and the chosen ones
on the test sets, each at several noise seeds.

    python experiments/real_camera.py --out experiments/results/real_camera
    python experiments/real_camera.py --policy runs/x/policy --looks 0,30 --stops 0.8 --heldout 300:5

The conditions are the robustness table's real-camera rows
(:data:`regrasp_mjx.inference.robustness.CAMERA_CONDITIONS`: the tools and the needle seen by the
camera, calibration 5 mm / 3 deg, joint offsets up to 0.5; white tool noise 0.5 and 1.0 mm, a needle
bias of 0.5 and 1.0 mm, the ``lab-good`` and ``lab-typical`` presets) and the 0.25 mm row they are
measured against. Fused closed loop, shielded, judged on the true poses. The choice maximises the
mean success over the rows but the 1 mm needle bias (a bias as large as the success test's own
tolerance: reported, not chosen for); equals go to fewer frames. The time spent holding still (the
warm-up and the looks, at 30 frames per second) is each row's; the motion's own time is
experiments/execution_time.py's.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from regrasp_mjx.core.atomic import dumps, write_results
from regrasp_mjx.inference import robustness
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world.sampling import load_testset
from regrasp_mjx.world.testsets import make_testset

BASELINE = next(c for c in robustness.ROBOT_CONDITIONS if c.name == "calibration 5 mm 3 deg (camera)")
CONDITIONS = (BASELINE, *robustness.CAMERA_CONDITIONS)
NOT_CHOSEN_FOR = "camera: needle bias 1.0 mm"


def measure(policy, episodes, look: int, stop: float, seed: int, log=print) -> list[dict]:
    rows = []
    for c in CONDITIONS:
        r = robustness.measure(policy, episodes, c, "fused", seed, look_frames=look, stop_tolerance=stop)
        rows.append({**r, "look_frames": look, "stop_tolerance": stop})
        log(dumps({k: rows[-1][k] for k in ("condition", "look_frames", "stop_tolerance", "seed", "success_rate")}))
    return rows


def chosen_score(rows: list[dict]) -> float:
    return float(np.mean([r["success_rate"] for r in rows if r["condition"] != NOT_CHOSEN_FOR]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=None, help="policy folder or shipped name (default: the shipped one)")
    p.add_argument("--looks", default="0,20,40,60", help="look budgets to choose from (frames), comma-separated")
    p.add_argument("--stops", default="0.6,0.7,0.8", help="stop tolerances to choose from, comma-separated")
    p.add_argument("--val-n", type=int, default=1000, help="validation problems")
    p.add_argument("--val-seed", type=int, default=7000017, help="their seed (never a test set's)")
    p.add_argument("--testset", default="paper300")
    p.add_argument("--heldout", default="3000:2022", metavar="N:SEED", help="held-out problems drawn here")
    p.add_argument("--seeds", default="0,1", help="noise seeds of the test runs, comma-separated")
    p.add_argument(
        "--validation", default=None, metavar="JSON", help="an earlier run's NAME_validation.json: its choice"
    )
    p.add_argument("--out", default=None)
    p.add_argument("--name", default="real_camera")
    args = p.parse_args()
    policy = load_policy(args.policy)
    own = policy.closed_loop_defaults
    if args.validation:  # the choice made before (the validation problems are not run again)
        grid, best = (json.loads(Path(args.validation).read_text())[k] for k in ("grid", "best"))
        best = next(g for g in grid if g == best)
    else:
        val = make_testset(args.val_n, args.val_seed, policy.env_config)
        grid = []
        for look, stop in itertools.product([int(x) for x in args.looks.split(",")], map(float, args.stops.split(","))):
            rows = measure(policy, val, look, stop, seed=1)
            frames = float(np.mean([r["frames_median"] for r in rows]))
            grid.append({"look_frames": look, "stop_tolerance": stop, "score": chosen_score(rows), "frames": frames})
        best = max(grid, key=lambda g: (round(g["score"], 6), -g["frames"]))
        write_results(args.out, f"{args.name}_validation", [dumps(g) for g in grid], {"grid": grid, "best": best})
    settings = {
        "own": (own["look_frames"], own["stop_tolerance"]),
        "chosen": (best["look_frames"], best["stop_tolerance"]),
    }
    n, _, seed = args.heldout.partition(":")
    sets = {args.testset: load_testset(args.testset)[0], f"held-out {n} (seed {seed})": make_testset(int(n), int(seed))}
    results = []
    for (setting, (look, stop)), (set_name, episodes) in itertools.product(settings.items(), sets.items()):
        for s in [int(x) for x in args.seeds.split(",")]:
            for r in measure(policy, episodes, look, stop, s):
                results.append({**r, "setting": setting, "problems_name": set_name})
    lines = [
        f"Policy `{args.policy or 'default'}` (hash {robustness.policy_hash(args.policy)}) under a real camera's "
        "errors: fused closed loop, shielded, tools and needle seen by the camera, calibration 5 mm / 3 deg, joint "
        "offsets up to 0.5; judged on the true poses.",
        "",
        f"Chosen on {args.val_n} validation problems (seed {args.val_seed}), mean success over the rows but "
        f"'{NOT_CHOSEN_FOR}':",
        "",
        "| look frames | stop tolerance | mean success | frames fused, median |",
        "| ---: | ---: | ---: | ---: |",
        *(
            f"| {g['look_frames']} | {g['stop_tolerance']:g} | {'**' if g is best else ''}{g['score']:.3f}"
            f"{'**' if g is best else ''} | {g['frames']:.0f} |"
            for g in grid
        ),
    ]
    seeds = args.seeds.replace(",", ", ")
    for set_name in sets:
        lines += [
            "",
            f"{set_name}, noise seeds {seeds}: success mean (min-max over seeds); collisions / stopped short of the "
            "true goal (means); time holding still, median / p95 (s, the worse seed). Own: look "
            f"{settings['own'][0]}, stop {settings['own'][1]:g}; chosen: look {settings['chosen'][0]}, stop "
            f"{settings['chosen'][1]:g}.",
            "",
            "| the camera's errors | own: success | own: coll. / wrong stop | own: still (s) | chosen: success "
            "| chosen: coll. / wrong stop | chosen: still (s) |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for c in CONDITIONS:
            cells = []
            for setting in settings:
                rs = [
                    r
                    for r in results
                    if (r["condition"], r["setting"], r["problems_name"]) == (c.name, setting, set_name)
                ]
                ok = [r["success_rate"] for r in rs]
                coll = np.mean([r["collision_rate"] for r in rs])
                wrong = np.mean([r["wrong_stop_rate"] for r in rs])
                still = max((r["still_s"] for r in rs), key=lambda x: x[1])
                cells += [
                    f"{np.mean(ok):.3f} ({min(ok):.3f}-{max(ok):.3f})",
                    f"{coll:.3f} / {wrong:.3f}",
                    f"{still[0]:.2f} / {still[1]:.2f}",
                ]
            lines.append(f"| {c.name.removeprefix('camera: ')} | " + " | ".join(cells) + " |")
    print("\n".join(lines))
    write_results(args.out, args.name, lines, {"grid": grid, "best": best, "settings": settings, "rows": results})


if __name__ == "__main__":
    main()
