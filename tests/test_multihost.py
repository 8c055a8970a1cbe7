"""Training across processes (hosts) with ``jax.distributed``: two local CPU processes with two fake
devices each end with the same parameters and checkpoint as one process with four.

Each process is a child (JAX fixes its device count and distributed setup when it starts); this
module is also the children's script. The coordinator listens on a free localhost port; CPU
collectives between the processes go through gloo.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from regrasp_mjx.agents.ddpg_bc import checkpoint

ROOT = Path(__file__).resolve().parent.parent
# several processes, each compiling a learner: in the long tier (see tests/conftest.py)
pytestmark = pytest.mark.slow

# A few iterations of a tiny data-parallel learner (one seed, environments split over 4 devices);
# ``ddpg_bc`` has no planner exchange, whose timing would differ between runs.
TRAIN_ARGS = [
    "--preset=smoke",
    "--exploration=ddpg_bc",
    "--devices=0",
    "--set=epochs=1",
    "--set=iterations_per_epoch=2",
    "--set=updates_per_iteration=3",
    "--set=hidden=(32,32)",
    "--set=batch_size=64",
    "--set=buffer_size=4096",
    "--set=demo_chunk=64",
    "--set=validation_size=8",
    "--set=distill.iterations=0",
    "--quiet",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _write_inputs(folder: Path) -> None:
    """Six random demonstration episodes and an 8-problem test set (values do not matter here)."""
    from regrasp_mjx.planning.episodes import save_demos
    from regrasp_mjx.world.sampling import save_testset
    from regrasp_mjx.world.testsets import make_testset

    rng = np.random.default_rng(0)
    episodes = [
        {
            "obs": rng.normal(size=(10, 21)),
            "action": rng.uniform(-1, 1, (10, 6)),
            "reward": np.full(10, -0.02),
            "done": np.r_[np.zeros(9), 1.0],
            "next_obs": rng.normal(size=(10, 21)),
            "problem_index": i,
            "path_length_mm": 4.0,
            "plan_time_s": 0.1,
        }
        for i in range(6)
    ]
    save_demos(folder / "demos" / "demos.npz", episodes, {})
    save_testset(folder / "tiny.npz", make_testset(8, 5), {})


def _child(folder: Path, out: Path, process_id: int | None, port: int | None) -> None:
    """One process of the run (``process_id`` None: the single four-device process)."""
    from regrasp_mjx import train

    argv = [*TRAIN_ARGS, f"--demos={folder / 'demos'}", f"--testset={folder / 'tiny.npz'}", f"--out={out}"]
    if process_id is not None:
        argv += [f"--coordinator=localhost:{port}", "--num-processes=2", f"--process-id={process_id}"]
    assert train.main(argv) == 0
    if process_id is None:
        return
    # The planner exchange's broadcast: process 0's chunks reach process 1, which has none.
    import types

    import jax

    from regrasp_mjx.agents.ddpg_bc.config import make_config
    from regrasp_mjx.agents.ddpg_bc.exchange import PlannerExchange
    from regrasp_mjx.envs.env import RegraspEnv

    assert jax.process_count() == 2 and jax.device_count() == 4
    cfg = make_config("smoke", demo_chunk=4)
    fake = types.SimpleNamespace(cfg=cfg, learner=types.SimpleNamespace(env=RegraspEnv(cfg.env)))
    rng = np.random.default_rng(7)
    sent = [
        (m, {k: rng.normal(size=(4, *s)).astype(np.float32) for k, s in shapes})
        for m, shapes in ((1, _SHAPES), (0, _SHAPES))
    ]
    got = PlannerExchange.broadcast_chunks(fake, sent if process_id == 0 else [])
    ok = [m for m, _ in got] == [1, 0] and all(
        np.array_equal(g[1][k], s[1][k]) for g, s in zip(got, sent) for k in g[1]
    )
    (out / f"broadcast{process_id}.json").write_text(json.dumps({"ok": bool(ok), "n": len(got)}))


_SHAPES = (("obs", (21,)), ("action", (6,)), ("reward", ()), ("next_obs", (21,)), ("terminal", ()))


def _launch(folder: Path, out: Path, devices: int, process_id: int | None = None, port: int | None = None):
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}".strip(),
        "PYTHONPATH": str(ROOT),
    }
    args = [sys.executable, __file__, str(folder), str(out), str(-1 if process_id is None else process_id), str(port)]
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _wait(proc, name: str) -> None:
    try:
        log, _ = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        proc.kill()
        log, _ = proc.communicate()
        pytest.fail(f"{name} did not finish in 600 s:\n{log[-3000:]}")
    assert proc.returncode == 0, f"{name} failed:\n{log[-3000:]}"


def test_two_processes_match_one_process_of_four_devices(tmp_path, alone):
    _write_inputs(tmp_path)
    with alone():  # the two processes must reach their first collective within 30 s of each other
        port = _free_port()
        procs = [_launch(tmp_path, tmp_path / "two", 2, i, port) for i in (0, 1)]
        for i, proc in enumerate(procs):
            _wait(proc, f"process {i}")
    _wait(_launch(tmp_path, tmp_path / "one", 4), "the single process")

    two, one = tmp_path / "two", tmp_path / "one"
    # process 0 alone writes the run's files
    assert (two / "log.jsonl").is_file() and (two / "policy_last" / "policy.npz").is_file()
    for name in ("policy_last/policy.npz", "checkpoint/state.npz"):
        with np.load(two / name) as a, np.load(one / name) as b:
            assert a.files == b.files
            # relative: the normaliser's running sums reach the hundreds (float32: 1e-4 apart is a few ulps)
            worst = max(
                float(np.max(np.abs(a[k].astype(np.float64) - b[k]) / (1.0 + np.abs(b[k].astype(np.float64)))))
                for k in a.files
                if k != checkpoint.META  # the state's own metadata (the run's id differs)
            )
        assert worst < 1e-6, (name, worst)
    logs = [json.loads((d / "log.jsonl").read_text().splitlines()[-1]) for d in (two, one)]
    assert logs[0]["train_collision"] == logs[1]["train_collision"]
    for i in (0, 1):
        assert json.loads((two / f"broadcast{i}.json").read_text()) == {"ok": True, "n": 2}


if __name__ == "__main__":
    folder, out, pid, port = sys.argv[1:5]
    _child(Path(folder), Path(out), None if pid == "-1" else int(pid), None if port == "None" else int(port))
