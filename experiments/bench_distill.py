"""Time of one distillation iteration (``python -m regrasp_mjx.distill``'s jitted DAgger step: the
student's rollouts, the teacher's labels with their lookahead rollouts, the updates), with rows that
have ended stepped by no motion (``rollout.HOLD_STILL``, as shipped) and by their own action (before).

The recipe's students spend their time here: 20 iterations each, six of them for the shipped
default. The labels' lookahead rolls 26 candidate actions out from each of 16,384 states for up to
40 steps; a row that has ended (in the wire, say) and is stepped by its own action again is, we
infer, the continuous collision test's costliest case: a motion from inside the wire, bisected to
the test's budget.

    python experiments/bench_distill.py --teacher runs/d/teachers/seed0/policy --out experiments/results/recipe/distill
    python experiments/bench_distill.py --teacher decay --iterations 3        # a shipped policy as the teacher

Compile time is in the first two iterations (one program for every iteration since the first's teacher
rollout became a traced flag); the others are timed one by one.
"""

from __future__ import annotations

import argparse
import time

import jax

from regrasp_mjx.agents.dagger import DistillConfig, Distiller, aim
from regrasp_mjx.core.atomic import dumps, machine, write_results
from regrasp_mjx.core.config import parse_overrides, replace
from regrasp_mjx.envs import rollout
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.workflows.recipes import RECIPES


def bench(teacher, cfg: DistillConfig, iterations: int, hold_still: bool) -> dict:
    rollout.HOLD_STILL = hold_still  # read when the iteration is traced: a new Distiller traces anew
    distiller = Distiller(RegraspEnv(aim(teacher.env_config, cfg)), teacher.network(), cfg)
    ds, times, metrics = distiller.init(), [], []
    for i in range(iterations + 2):
        t0 = time.perf_counter()
        ds, m = distiller.iteration(ds, i == 0)
        metrics.append({k: float(v) for k, v in jax.device_get(m).items()})
        times.append(time.perf_counter() - t0)
    steady = times[2:]
    return {
        "hold_still": hold_still,
        "compile_and_first_two_s": times[0] + times[1],
        "iteration_s": steady,
        "median_iteration_s": sorted(steady)[len(steady) // 2],
        "metrics": metrics,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--teacher", default="decay", help="teacher policy folder or shipped name")
    p.add_argument("--recipe", default="default", help="the recipe whose first student variant's settings are used")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a DistillConfig field")
    p.add_argument("--iterations", type=int, default=3, help="timed iterations after the first two")
    p.add_argument("--modes", default="held,own", help="held (ended rows stepped by no motion), own (by their action)")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    recipe = RECIPES[args.recipe]
    variant = recipe.students.variants[0][0]
    cfg = replace(recipe.student_config(variant), **parse_overrides(args.set))
    teacher = load_policy(args.teacher)
    rows = []
    for mode in args.modes.split(","):
        if mode not in ("held", "own"):
            p.error(f"--modes {mode!r} is not accepted: held, own")
        rows.append(bench(teacher, cfg, args.iterations, mode == "held"))
        print(dumps({k: v for k, v in rows[-1].items() if k != "metrics"}), flush=True)
    where = machine()
    lines = [
        f"{where}; teacher {args.teacher}; recipe {args.recipe}'s student `{variant}` ({cfg.problems} problems, "
        f"{cfg.label_states} labelled states, lookahead {cfg.lookahead}, {cfg.updates} updates an iteration).",
        "",
        "| ended rows stepped by | compile + first two (s) | iteration (s), median | iterations (s) |",
        "| --- | ---: | ---: | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {'no motion' if r['hold_still'] else 'their own action'} | {r['compile_and_first_two_s']:.1f} | "
            f"{r['median_iteration_s']:.2f} | {', '.join(f'{t:.2f}' for t in r['iteration_s'])} |"
        )
    print("\n".join(lines))
    write_results(args.out, "bench_distill", lines, {"machine": where, "teacher": args.teacher, "rows": rows})


if __name__ == "__main__":
    main()
