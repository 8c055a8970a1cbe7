"""A policy under a real camera's errors (issue 67): the closed loop's look budget, stop tolerance and
jaw opening (the widest the jaws may open before the first move, and the margin in the view's known
errors the opening keeps: regrasp_mjx/inference/jaw_opening.py) chosen on validation problems of
their own seed, then the policy's own settings and the chosen ones on the test sets, each at several
noise seeds.

    python experiments/real_camera.py --out experiments/results/real_camera
    python experiments/real_camera.py --policy runs/x/policy --looks 0,30 --stops 0.8 --heldout 300:5
    python experiments/real_camera.py --looks 0,60 --stops 0.7 --jaws 20,40,60 --jaw-sigmas 1,2,3 \
        --out experiments/results/jaw_opening

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

from regrasp_mjx.core.atomic import dumps, machine, write_results
from regrasp_mjx.inference import robustness
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.world.sampling import load_testset
from regrasp_mjx.world.testsets import make_testset

BASELINE = next(c for c in robustness.ROBOT_CONDITIONS if c.name == "calibration 5 mm 3 deg (camera)")
CONDITIONS = (BASELINE, *robustness.CAMERA_CONDITIONS)
NOT_CHOSEN_FOR = "camera: needle bias 1.0 mm"


KNOBS = ("look_frames", "stop_tolerance", "jaw_deg", "jaw_sigmas")  # the closed loop's settings chosen here


def measure(policy, episodes, setting: dict, seed: int, log=print) -> list[dict]:
    rows = []
    for c in CONDITIONS:
        r = robustness.measure(policy, episodes, c, "fused", seed, **setting)
        rows.append({**r, **setting})
        log(dumps({k: rows[-1][k] for k in ("condition", *KNOBS, "seed", "success_rate", "opened_rate")}))
    return rows


def settings_grid(args, policy) -> list[dict]:
    """Every setting to choose from; the jaw's margin only where the jaws may open (before the first move,
    or on the way for a policy trained to: its jaws at the scene's opening to start with)."""
    base = policy.env_config.scene.jaw_angle_deg
    on_the_way = policy.env_config.jaw_open_deg is not None
    values = [[float(x) for x in v.split(",")] for v in (args.looks, args.stops, args.jaws, args.jaw_sigmas)]
    grid = []
    for look, stop, jaw, sigmas in itertools.product(*values):
        jaw, sigmas = (base, sigmas) if on_the_way else (jaw, sigmas * (jaw > base))
        g = {"look_frames": int(look), "stop_tolerance": stop, "jaw_deg": jaw, "jaw_sigmas": sigmas}
        if g not in grid:
            grid.append(g)
    return grid


def describe(knobs: dict, policy) -> str:
    if policy.env_config.jaw_open_deg is not None:
        jaw = f"jaws open on the way to {policy.env_config.jaw_open_deg:g} deg at {knobs['jaw_sigmas']:g} sd"
    elif knobs["jaw_sigmas"]:
        jaw = f"jaws to {knobs['jaw_deg']:g} deg at {knobs['jaw_sigmas']:g} sd"
    else:
        jaw = "jaws kept"
    return f"look {knobs['look_frames']}, stop {knobs['stop_tolerance']:g}, {jaw}"


def _frames(g: dict) -> str:
    return "-" if g["frames"] is None else f"{g['frames']:.0f}"  # None: not logged by a merged grid


def chosen_score(rows: list[dict]) -> float:
    return float(np.mean([r["success_rate"] for r in rows if r["condition"] != NOT_CHOSEN_FOR]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=None, help="policy folder or shipped name (default: the shipped one)")
    p.add_argument("--looks", default="0,20,40,60", help="look budgets to choose from (frames), comma-separated")
    p.add_argument("--stops", default="0.6,0.7,0.8", help="stop tolerances to choose from, comma-separated")
    p.add_argument(
        "--jaws", default="20", help="widest jaw openings to choose from (deg; 20 keeps the jaws), comma-separated"
    )
    p.add_argument(
        "--start-jaw",
        type=float,
        default=None,
        help="plan with the jaws at this opening where they are not opened (deg; e.g. 20 for a policy trained at 40)",
    )
    p.add_argument("--jaw-sigmas", default="2", help="the opening's margins in the view's errors, comma-separated")
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
    if args.start_jaw is not None:
        policy = policy.with_env(**{"scene.jaw_angle_deg": args.start_jaw})
    own = policy.closed_loop_defaults
    if args.validation:  # the choice made before (the validation problems are not run again)
        grid, best = (json.loads(Path(args.validation).read_text())[k] for k in ("grid", "best"))
        best = next(g for g in grid if g == best)
    else:
        val = make_testset(args.val_n, args.val_seed, policy.env_config)
        grid = []
        for setting in settings_grid(args, policy):
            rows = measure(policy, val, setting, seed=1)
            frames = float(np.mean([r["frames_median"] for r in rows]))
            grid.append({**setting, "score": chosen_score(rows), "frames": frames})
        best = max(grid, key=lambda g: (round(g["score"], 6), -g["frames"], -g["jaw_deg"]))
        write_results(args.out, f"{args.name}_validation", [dumps(g) for g in grid], {"grid": grid, "best": best})
    kept = {"jaw_deg": policy.env_config.scene.jaw_angle_deg, "jaw_sigmas": 0.0}  # an earlier run's choice
    settings = {
        "own": {k: own[k] for k in KNOBS},
        "chosen": {k: best.get(k, kept.get(k)) for k in KNOBS},
    }
    if settings["own"]["jaw_deg"] is None:  # the policy keeps its jaws
        settings["own"].update(kept)
    n, _, seed = args.heldout.partition(":")
    sets = {args.testset: load_testset(args.testset)[0], f"held-out {n} (seed {seed})": make_testset(int(n), int(seed))}
    results = []
    for (setting, knobs), (set_name, episodes) in itertools.product(settings.items(), sets.items()):
        if setting == "chosen" and knobs == settings["own"]:  # the policy's file holds the choice: measured once
            same = [r for r in results if (r["setting"], r["problems_name"]) == ("own", set_name)]
            results += [{**r, "setting": "chosen"} for r in same]
            continue
        for s in [int(x) for x in args.seeds.split(",")]:
            for r in measure(policy, episodes, knobs, s):
                results.append({**r, "setting": setting, "problems_name": set_name})
    lines = [
        f"Policy `{args.policy or 'default'}` (hash {robustness.policy_hash(args.policy)}) under a real camera's "
        "errors: fused closed loop, shielded, tools and needle seen by the camera, calibration 5 mm / 3 deg, joint "
        "offsets up to 0.5; judged on the true poses.",
        "",
        f"Measured on {machine()}" + (f"; the choice from {args.validation}" if args.validation else "") + ".",
        "",
        f"Chosen on {args.val_n} validation problems (seed {args.val_seed}), mean success over the rows but "
        f"'{NOT_CHOSEN_FOR}':",
        "",
        "| look frames | stop tolerance | jaw, widest (deg) | jaw margin (sd) | mean success | frames fused, median |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
        *(
            f"| {g['look_frames']} | {g['stop_tolerance']:g} | {g['jaw_deg']:g} | {g['jaw_sigmas']:g} | "
            f"{'**' if g is best else ''}{g['score']:.3f}{'**' if g is best else ''} | {_frames(g)} |"
            for g in grid
        ),
    ]
    seeds = args.seeds.replace(",", ", ")
    for set_name in sets:
        lines += [
            "",
            f"{set_name}, noise seeds {seeds}: success mean (min-max over seeds); collisions / stopped short of the "
            "true goal (means; the opening sweep's collisions, a part of them, after the slash); jaws opened "
            "(mean share); time holding still, median / p95 (s, the worse seed). Own: "
            f"{describe(settings['own'], policy)}; chosen: {describe(settings['chosen'], policy)}.",
            "",
            "| the camera's errors | own: success | own: coll. / wrong stop | own: still (s) | chosen: success "
            "| chosen: coll. (opening) / wrong stop | chosen: opened | chosen: still (s) |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
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
                opening = np.mean([r["opening_collision_rate"] for r in rs])
                opened = np.mean([r["opened_rate"] for r in rs])
                cells += [f"{np.mean(ok):.3f} ({min(ok):.3f}-{max(ok):.3f})"]
                if setting == "own":
                    cells += [f"{coll:.3f} / {wrong:.3f}"]
                else:
                    cells += [f"{coll:.3f} ({opening:.3f}) / {wrong:.3f}", f"{opened:.2f}"]
                cells += [f"{still[0]:.2f} / {still[1]:.2f}"]
            lines.append(f"| {c.name.removeprefix('camera: ')} | " + " | ".join(cells) + " |")
    print("\n".join(lines))
    data = {"grid": grid, "best": best, "settings": settings, "machine": machine(), "rows": results}
    write_results(args.out, args.name, lines, data)


if __name__ == "__main__":
    main()
