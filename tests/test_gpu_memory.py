"""GPU memory: the training state's size by hand, the allocator settings, and the messages."""

from __future__ import annotations

import dataclasses

import pytest

from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.core import gpu_memory
from regrasp_mjx.core.config import ConfigError


def test_state_bytes_by_hand():
    # hidden (4,): actor 21*4+4 + 4*6+6 = 118; two critics of 27*4+4 + 4*1+1 = 117 each = 234;
    # networks 5*118 + 4*234 = 1526 floats; buffers (10 + 5) transitions of 50 floats = 750;
    # 2 learners x (1526 + 750) floats x 4 bytes = 18208
    cfg = dataclasses.replace(TrainConfig(), hidden=(4,), buffer_size=10, batch_size=8, num_seeds=2)
    assert gpu_memory.state_bytes(cfg, demo_transitions=5) == 18208
    # our learner, 3 seeds: the three buffers of 1.1e6 transitions (220 MB each) dominate, 0.74 GB
    assert 0.74e9 < gpu_memory.state_bytes(dataclasses.replace(TrainConfig(), num_seeds=3)) < 0.75e9


def test_settings_set_jax_allocator_variables(monkeypatch):
    for var in ("XLA_PYTHON_CLIENT_MEM_FRACTION", "XLA_PYTHON_CLIENT_PREALLOCATE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(gpu_memory, "other_processes_on_gpu", lambda: 0)
    assert gpu_memory.configure(gpu_memory.parse_setting("0.45")) == "0.45"
    assert gpu_memory.os.environ["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.45"
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION")
    assert gpu_memory.configure(None) is None  # alone on the GPU: JAX's default
    said = []
    monkeypatch.setattr(gpu_memory, "other_processes_on_gpu", lambda: 1)
    assert gpu_memory.configure(None, log=said.append) == "grow"  # another run holds the GPU
    assert gpu_memory.os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false" and "another process" in said[0]
    assert gpu_memory.configure("0.3") is None  # a variable the user set is left alone
    for bad in ("0", "1.5", "half"):
        with pytest.raises(ConfigError, match="--gpu-memory .* is not accepted"):
            gpu_memory.parse_setting(bad)


def test_out_of_memory_is_recognised_and_explained():
    assert gpu_memory.is_out_of_memory(RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate"))
    assert not gpu_memory.is_out_of_memory(RuntimeError("INVALID_ARGUMENT: shapes"))
    msg = gpu_memory.out_of_memory_message(dataclasses.replace(TrainConfig(), num_seeds=3))
    assert "about 0.7 GiB" in msg and "3 learner(s)" in msg and "--gpu-memory 0.45" in msg
