"""How much GPU memory a training run takes, and how several runs share one GPU.

JAX pre-allocates 75 % of a GPU's memory when its GPU client starts, so a second training process
on the same GPU finds too little left and dies with CUDA out-of-memory. ``--gpu-memory`` (train
CLI) sets JAX's documented allocator variables before its client starts: a fraction
(``XLA_PYTHON_CLIENT_MEM_FRACTION``: pre-allocate that share) or ``grow``
(``XLA_PYTHON_CLIENT_PREALLOCATE=false``: allocate as needed). Left unset, a run whose GPU already
runs another process grows instead of pre-allocating, and says so. A run that still runs out of
memory ends with a message naming what its training state takes and what to set.
"""

from __future__ import annotations

import os
import shutil
import subprocess

from regrasp_mjx.core.config import ConfigError

OBS, ACTION = 21, 6  # the environment's observation and action sizes
TRANSITION_FLOATS = 2 * OBS + ACTION + 2  # obs, next_obs, action, reward, terminal


def _mlp_params(sizes: list[int]) -> int:
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


def state_bytes(cfg, demo_transitions: int = 100_000) -> int:
    """Bytes of the training state of all learners in a run (float32): replay buffers, networks with
    their targets, Adam moments and the actor's moving average. XLA's working memory comes on top."""
    hidden = list(cfg.hidden)
    actor = _mlp_params([OBS, *hidden, ACTION])
    critic = cfg.critics * _mlp_params([OBS + ACTION, *hidden, 1])
    networks = 5 * actor + 4 * critic  # actor: params, EMA, target, 2 moments; critic: params, target, 2 moments
    buffers = (cfg.buffer_size + demo_transitions) * TRANSITION_FLOATS
    return 4 * cfg.num_members * (networks + buffers)


def parse_setting(value: str | None) -> str | None:
    """``None``, ``"grow"`` or a fraction in (0, 1] as a string; raises :class:`ConfigError` otherwise."""
    if value is None or value == "grow":
        return value
    try:
        fraction = float(value)
    except ValueError:
        fraction = -1.0
    if not 0.0 < fraction <= 1.0:
        raise ConfigError(
            f"--gpu-memory {value!r} is not accepted: a fraction in (0, 1] of the GPU to pre-allocate "
            "(e.g. 0.45 for each of two runs sharing one GPU) or 'grow' (allocate as needed)"
        )
    return f"{fraction:g}"


def other_processes_on_gpu() -> int:
    """Compute processes already running on the GPU(s) this process would use (0 when unknown)."""
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return 0
    query = [smi, "--query-compute-apps=gpu_uuid", "--format=csv,noheader"]
    try:
        apps = subprocess.run(query, capture_output=True, text=True, timeout=20).stdout.split()
        gpus = subprocess.run(
            [smi, "--query-gpu=index,uuid", "--format=csv,noheader"], capture_output=True, text=True, timeout=20
        ).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return 0
    uuid = {line.split(",")[0].strip(): line.split(",")[1].strip() for line in gpus if "," in line}
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    mine = {uuid.get(i.strip(), i.strip()) for i in visible.split(",")} if visible else set(uuid.values())
    return sum(1 for a in apps if a in mine)


def configure(setting: str | None, log=print) -> str | None:
    """Sets JAX's allocator variables for ``setting`` (call before JAX starts its GPU client);
    returns what was chosen. Variables the user set in the environment are left as they are."""
    if "XLA_PYTHON_CLIENT_MEM_FRACTION" in os.environ or "XLA_PYTHON_CLIENT_PREALLOCATE" in os.environ:
        return None
    if setting is None and other_processes_on_gpu() > 0:
        setting = "grow"
        log("another process runs on this GPU: allocating GPU memory as needed (--gpu-memory grow)")
    if setting == "grow":
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    elif setting is not None:
        os.environ["XLA_PYTHON_CLIENT_MEM_FRACTION"] = setting
    return setting


def is_out_of_memory(err: BaseException) -> bool:
    text = str(err)
    return "RESOURCE_EXHAUSTED" in text or "Out of memory" in text or "out of memory" in text


def out_of_memory_message(cfg) -> str:
    need = state_bytes(cfg) / 2**30
    return (
        f"the GPU ran out of memory. This run's training state takes about {need:.1f} GiB "
        f"({cfg.num_members} learner(s), replay buffers of {cfg.buffer_size:,} transitions each), plus "
        "XLA's working memory. If another process holds the GPU (nvidia-smi lists it), give each run "
        "its share: --gpu-memory 0.45 for each of two runs, or --gpu-memory grow; otherwise lower "
        "--seeds or --set buffer_size=..."
    )
