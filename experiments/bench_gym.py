"""The gymnasium vector env's speed, with numpy and with device arrays, against the raw MJX env's.

Issue 49 measured it; issue 71's targets: at least 0.9 of the raw one-jitted-step-per-call rate with
device arrays, 0.7 with numpy arrays, at 4,096 envs on one GPU.

Raw, the scan: ``bench_env``'s rollout (``AutoResetWrapper(VmapWrapper(RegraspEnv))``, a reset and
then random actions drawn on the device, all steps in one jitted ``lax.scan``, nothing back to the
host but three sums). Raw, per call: the same wrapped env stepped one jitted step per call (device
actions, nothing back to the host, dispatched ahead): what any step-at-a-time API must do, so the
table tells the vector env's own cost from the cost of leaving the scan; the issue's targets are
against this row ("x per call").

gymnasium: ``make_vec("regrasp_mjx/NeedleRegrasp-v0", num_envs=B, vectorization_mode="vector_entry_point",
autoreset_mode=MODE, arrays=ARRAYS)`` stepped from Python with actions made before the clock starts:
``arrays="numpy"`` with numpy actions, every step's observation dict, rewards, flags and infos on the
host as numpy arrays (what a numpy learner gets); ``arrays="jax"`` with device actions, every output
a jax array left on the device (what a learner written in JAX gets), the clock stopped once the last
step's outputs are ready. Same-step and next-step autoreset draw a new problem for every ended episode
(from a pool drawn ahead); the raw rows restore the episode's first state instead.

The per-call and gymnasium rows are compiled first and then timed in turns (repeat r of every row,
then r + 1), so that a machine whose load drifts weighs on each alike; each row's rate is over all
its timed repeats (the pool's redraws, which come every few dozen steps, counted where they fall).
Compile time is excluded; env-steps/s = B * steps * repeats / wall.

    python experiments/bench_gym.py --num-envs 4096 --out experiments/results/gym --name bench_gym_h200
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import jax
import numpy as np
from bench_env import bench_mjx
from brax.envs.wrappers.training import AutoResetWrapper, VmapWrapper

import regrasp_mjx  # noqa: F401  (registers the ids)
from regrasp_mjx.core.atomic import machine, write_results
from regrasp_mjx.core.config import EnvConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.interfaces import gym_programs

MODES = ("same_step", "next_step", "disabled")
ARRAYS = ("numpy", "jax")


class StepCalls:
    """The raw env stepped as a step API must step it: one jitted step per call (device actions,
    nothing back to the host, dispatched ahead), under the same wrappers as the scan."""

    def __init__(self, batch: int, steps: int, seed: int):
        self.name, self.batch, self.steps = "raw MJX env, one jitted step per call", batch, steps
        wrapped = AutoResetWrapper(VmapWrapper(RegraspEnv(EnvConfig())))
        self.step = jax.jit(wrapped.step)
        actions = jax.random.uniform(jax.random.PRNGKey(seed), (steps, batch, 6), minval=-1.0, maxval=1.0)
        self.actions = [actions[i] for i in range(steps)]  # sliced before the clock
        t0 = time.perf_counter()
        self.state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(seed), batch))
        jax.block_until_ready(self.step(self.state, self.actions[0]))
        self.compile_s, self.walls, self.ended = time.perf_counter() - t0, [], None  # not counted: nothing read

    def run(self, r: int) -> None:
        state = self.state
        t0 = time.perf_counter()
        for a in self.actions:
            state = self.step(state, a)
        jax.block_until_ready(state)
        self.walls.append(time.perf_counter() - t0)
        self.state = state


class Vector:
    """The gymnasium vector env in one autoreset mode and array kind."""

    def __init__(self, batch: int, steps: int, mode: str, arrays: str, seed: int):
        self.name, self.batch, self.steps = f"gymnasium vector ({mode}, {arrays} arrays)", batch, steps
        self.mode, self.arrays, self.seed = mode, arrays, seed
        self.envs = gymnasium.make_vec(
            "regrasp_mjx/NeedleRegrasp-v0",
            num_envs=batch,
            vectorization_mode="vector_entry_point",
            autoreset_mode=mode,
            arrays=arrays,
        )
        actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, batch, 6)).astype(np.float32)
        if arrays == "jax":
            actions = jax.device_put(actions)
        self.actions = [actions[i] for i in range(steps)]  # sliced (and on the device) before the clock
        t0 = time.perf_counter()
        self.envs.reset(seed=seed)
        jax.block_until_ready(self.envs.step(self.actions[0]))  # compiles
        self.compile_s, self.walls, self.ended = time.perf_counter() - t0, [], 0

    def run(self, r: int) -> None:
        jax.block_until_ready(self.envs.reset(seed=self.seed + 1 + r))
        flags = []
        t0 = time.perf_counter()
        for a in self.actions:
            _, _, terminated, truncated, _ = self.envs.step(a)
            flags.append((terminated, truncated))
        jax.block_until_ready(flags[-1])
        self.walls.append(time.perf_counter() - t0)
        self.ended += sum(int(np.sum(np.asarray(t) | np.asarray(u))) for t, u in flags)


def row(bench, repeats: int) -> dict:
    wall = sum(bench.walls)
    return {
        "backend": bench.name,
        "batch": bench.batch,
        "steps": bench.steps,
        "repeats": repeats,
        "compile_s": round(bench.compile_s, 2),
        "wall_s": round(wall, 4),
        "fastest_repeat_s": round(min(bench.walls), 4),
        "env_steps_per_s": bench.batch * bench.steps * repeats / wall,
        "episodes_ended": bench.ended,
    }


def choices(text: str, accepted: tuple[str, ...], flag: str) -> list[str]:
    picked = [x for x in text.split(",") if x]
    wrong = [x for x in picked if x not in accepted]
    if wrong or not picked:
        raise SystemExit(f"{flag} {text!r} is not accepted: a comma-separated list of {', '.join(accepted)}")
    return picked


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--num-envs", "--batch-sizes", dest="num_envs", default="4096", help="comma-separated numbers of envs"
    )
    p.add_argument("--steps", type=int, default=100, help="steps a timed repeat")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats of each row, taken in turns")
    p.add_argument("--modes", default=",".join(MODES), help="autoreset modes of the gymnasium rows")
    p.add_argument("--arrays", default=",".join(ARRAYS), help="array kinds of the gymnasium rows")
    p.add_argument("--no-scan", action="store_true", help="leave out the scan row (its compile is the longest)")
    p.add_argument(
        "--pool-per-env",
        type=int,
        default=gym_programs.Program.POOL_PER_ENV,
        help="fresh problems drawn ahead per env, all redrawn at once when used up (the module's by default)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="folder for NAME.md and NAME.json")
    p.add_argument("--name", default="bench_gym")
    args = p.parse_args()
    modes, arrays = choices(args.modes, MODES, "--modes"), choices(args.arrays, ARRAYS, "--arrays")
    sizes = [int(x) for x in args.num_envs.split(",")]
    if args.steps < 1 or args.repeats < 1 or min(sizes) < 1 or args.pool_per_env < 1:
        raise SystemExit("--num-envs, --steps, --repeats and --pool-per-env are not accepted below 1")
    gym_programs.Program.POOL_PER_ENV = args.pool_per_env  # read as each vector env is made
    rows = []
    for b in sizes:
        scan = None
        if not args.no_scan:
            scan = bench_mjx(EnvConfig(), b, args.steps, args.repeats, args.seed)
            scan["backend"] = "raw MJX env (scan)"
            print(scan, flush=True)
        benches = [StepCalls(b, args.steps, args.seed)]
        benches += [Vector(b, args.steps, m, a, args.seed) for a in arrays for m in modes]
        for r in range(args.repeats):
            for bench in benches:
                bench.run(r)
        found = [row(bench, args.repeats) for bench in benches]
        calls = found[0]["env_steps_per_s"]
        for x in ([scan] if scan else []) + found:
            x["of_scan"] = x["env_steps_per_s"] / scan["env_steps_per_s"] if scan else None
            x["of_calls"] = x["env_steps_per_s"] / calls
            rows.append(x)
            print(x, flush=True)
    where = machine()
    ratio = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [
        f"{where}, jax {jax.__version__}; {args.steps} steps of random actions, {args.repeats} repeats in turns; "
        f"a pool of {args.pool_per_env} problems per env",
        "",
        "| env | batch | env-steps/s | x the scan | x per call |",
        "| --- | ---: | ---: | ---: | ---: |",
        *(
            f"| {r['backend']} | {r['batch']:,} | {r['env_steps_per_s']:,.0f} | {ratio(r['of_scan'])} "
            f"| {ratio(r['of_calls'])} |"
            for r in rows
        ),
    ]
    write_results(args.out, args.name, lines, {"machine": where, "args": vars(args), "rows": rows})
    print("\n".join(lines))


if __name__ == "__main__":
    main()
