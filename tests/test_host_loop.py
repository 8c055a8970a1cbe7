"""The host loops' shared parts: phase timers, best-by-validation, the JSONL log, and checkpoints
written beside the training (one atomic file that carries its own metadata)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from regrasp_mjx.agents.ddpg_bc import checkpoint
from regrasp_mjx.core.host_loop import BestOf, Phases, RunLog, eta, release_programs


def test_phases_sum_repeats_and_start_anew():
    phases = Phases()
    for _ in range(3):
        with phases("wait"):
            time.sleep(0.01)
    phases.add("wait", 1.0)
    with pytest.raises(KeyError), phases("fails"):  # a phase that raises still counts
        {}["missing"]
    took = phases.take()
    assert 1.03 <= took["wait"] < 1.5 and "fails" in took
    assert phases.take() == {}
    phases.add("wait", 2.0)  # the run's totals add every take's, and what is not taken yet
    assert phases.totals()["wait"] == pytest.approx(took["wait"] + 2.0, abs=1e-3) and "fails" in phases.totals()


def test_best_of_keeps_the_later_of_equals_and_owns_no_copy():
    score, step = [-1.0, -1.0], [None, None]
    best = BestOf(score, step)
    assert best.update([0.5, 0.2], 1) == [0, 1]
    assert best.update([0.5, 0.1], 2) == [0]  # a tie counts: the later network is exported
    assert best.update([0.4, 0.3], 3) == [1]
    assert (score, step) == ([0.5, 0.3], [2, 3])  # the lists given (a checkpoint's meta) hold it
    with pytest.raises(ValueError, match="one of each per member"):
        BestOf([0.0], [])


def test_run_log_appends_and_drops_rows_after_a_checkpoint(tmp_path):
    class Writer:
        def __init__(self):
            self.seen = []

        def add_scalar(self, k, v, step):
            self.seen.append((k, v, step))

        def flush(self):
            pass

        def close(self):
            pass

    tb = Writer()
    log = RunLog(tmp_path / "log.jsonl", [tb, None])
    for epoch in (1, 2, 3):
        log.write([{"epoch": epoch, "test": {"success_rate": 0.5}, "x": float("nan")}, {"epoch": epoch}])
    log.drop_after("epoch", 2)
    assert [json.loads(x)["epoch"] for x in log.path.read_text().splitlines()] == [1, 1, 2, 2]
    assert ("test/success_rate", 0.5, 3) in tb.seen and not any(k == "x" for k, _, _ in tb.seen)  # finite only
    assert eta(2, 10, 60.0) == "ETA 4.0 min"


def test_checkpoint_writer_writes_in_the_background_and_raises_its_error(tmp_path):
    state = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.int32(7)}
    meta = {"epoch": 3, "config": {"x": 1}}
    writer = checkpoint.Writer()
    writer.save(tmp_path / "ckpt", state, meta)
    meta["epoch"] = 4  # the loop goes on: the checkpoint keeps what was given
    state["a"] += 1
    writer.wait()
    with np.load(tmp_path / "ckpt" / "state.npz") as f:
        np.testing.assert_array_equal(f["leaf_00000"], np.arange(6).reshape(2, 3))
        assert json.loads(str(f[checkpoint.META]))["epoch"] == 3
    assert json.loads((tmp_path / "ckpt" / "meta.json").read_text())["epoch"] == 3
    (tmp_path / "file").write_text("")
    writer.save(tmp_path / "file" / "ckpt", state, meta)  # a folder that cannot be made
    with pytest.raises(OSError):
        writer.wait()
    writer.wait()  # the error is raised once


def test_resume_trusts_the_state_files_own_metadata(tmp_path):
    """A kill between the state file and meta.json leaves an old meta.json beside the new state: the
    state's own copy is read."""
    from regrasp_mjx.agents.ddpg_bc.config import TrainConfig

    cfg = TrainConfig()
    state = {"a": np.zeros(3, np.float32)}
    writer = checkpoint.Writer()
    writer.save(tmp_path, state, {"epoch": 3, "config": checkpoint.config_json(cfg)})
    writer.wait()
    (tmp_path / "meta.json").write_text(json.dumps({"epoch": 2, "config": checkpoint.config_json(cfg)}))
    _, meta = checkpoint.load(tmp_path, state, cfg)
    assert meta["epoch"] == 3


def test_release_programs_drops_compiled_programs_only_above_the_bound():
    """Compiled programs are dropped (a jitted function's cache emptied) only when the process holds
    more memory maps than the bound: never at a bound no process reaches, always at 0."""
    import jax
    import jax.numpy as jnp

    f = jax.jit(lambda x: jnp.sin(x) * 3.0)
    f(jnp.ones(3))
    assert f._cache_size() == 1
    assert release_programs(10**9) is False and f._cache_size() == 1
    assert release_programs(0) is True and f._cache_size() == 0
    assert float(f(jnp.zeros(3))[0]) == 0.0  # compiles again where used
