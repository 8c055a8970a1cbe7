"""The Ray cluster that ``sweep`` and ``recipe`` run their jobs on (:mod:`regrasp_mjx.core.jobs`).

With no address named (no ``--address``, no ``RAY_ADDRESS``) a command starts Ray on this machine
itself, over every local GPU or those ``--gpus`` names, and stops it when it ends: nothing to set
up. ``--address HOST:PORT`` (or ``RAY_ADDRESS``) joins a running cluster (``ray start --head`` on one
host, ``ray start --address ...`` on the others: docs/training.md), whose nodes must see the run's
folder at the same path (a shared filesystem) and hold this package. A process that has already
called ``ray.init`` (a notebook, a test) keeps its Ray.

What the jobs are placed by is measured once when the command connects: the number of GPUs, the
smallest GPU's memory (each node asked by a task pinned to it, through ``nvidia-smi``; the shares
are of an 80 GB GPU, :data:`REFERENCE_MIB`, and are scaled to that smallest GPU), the fewest CPUs of a
node (what a GPU job's CPU ask is capped at) and the most (without GPUs a job takes that many, so one
job at a time runs on a node, as XLA on the CPU uses every core: :func:`regrasp_mjx.core.jobs.resources`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import subprocess
from collections.abc import Iterator

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from regrasp_mjx.core.config import ConfigError

# the memory the shares are of: an 80 GB H100 as nvidia-smi reports it [MiB]
REFERENCE_MIB = 81_559.0
# Ray's object store holds only the jobs' small records: the default (30 % of RAM) would reserve gigabytes
OBJECT_STORE_BYTES = 100 * 2**20


@dataclasses.dataclass(frozen=True)
class Cluster:
    """What the jobs are placed on. ``gpu_mib``: the smallest GPU's memory (None: not measured, the
    shares are taken as fractions as they are); ``node_cpus``: the fewest CPUs of a node; ``most_cpus``:
    the most (what a job takes without GPUs)."""

    address: str
    started_here: bool
    nodes: int
    gpus: float
    gpu_mib: float | None
    node_cpus: int
    dashboard: str | None
    most_cpus: int = 1

    @property
    def scale(self) -> float:
        """A share of an 80 GB GPU to a fraction of the smallest GPU here."""
        return REFERENCE_MIB / self.gpu_mib if self.gpu_mib else 1.0

    def describe(self) -> str:
        where = "Ray started on this machine" if self.started_here else f"Ray at {self.address}"
        what = f"{self.gpus:g} GPU(s)" if self.gpus else f"no GPU, {self.most_cpus} CPU(s) per job"
        board = f"; dashboard {self.dashboard}" if self.dashboard else ""
        return f"{where}: {self.nodes} node(s), {what}{board}"


def local_gpus(requested: str | None) -> list[str]:
    """The local GPU indices to start Ray over: ``--gpus`` (checked), else ``CUDA_VISIBLE_DEVICES``,
    else every one ``nvidia-smi`` lists; ``[]`` without a GPU. Asked of ``nvidia-smi``, not JAX: this
    process must not take GPU memory from its jobs."""
    if requested is not None:
        gpus = [g.strip() for g in requested.split(",")]
        if not gpus or not all(g.isdigit() for g in gpus):
            raise ConfigError(f"--gpus {requested!r} is not accepted: GPU indices, comma-separated (e.g. 0,2)")
        return gpus
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g.strip() for g in visible.split(",") if g.strip()]
    return [index for index, _ in _smi_memory()]


def _smi_memory() -> list[tuple[str, float]]:
    """``(index, total memory [MiB])`` of each GPU ``nvidia-smi`` lists here; ``[]`` without it."""
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return []
    query = [smi, "--query-gpu=index,memory.total", "--format=csv,noheader,nounits"]
    try:
        lines = subprocess.run(query, capture_output=True, text=True, timeout=30).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return []
    out = []
    for line in lines:
        index, _, mib = line.partition(",")
        try:
            out.append((index.strip(), float(mib)))
        except ValueError:
            continue
    return out


def add_options(parser, what: str) -> None:
    """``--gpus`` and ``--address``, as ``sweep`` and ``recipe`` take them (``what``: what they run)."""
    parser.add_argument(
        "--gpus", default=None, help="local GPU indices, comma-separated (default: every one nvidia-smi lists)"
    )
    parser.add_argument(
        "--address",
        default=None,
        help=f"a Ray cluster's head HOST:PORT to run the {what} on (default: RAY_ADDRESS, else Ray started here)",
    )


def check_options(address: str | None, gpus: str | None) -> str | None:
    """The cluster's address (``RAY_ADDRESS`` when None; None: Ray started here) once ``--gpus`` is
    checked: GPU indices, and only where Ray is started here."""
    address = address or os.environ.get("RAY_ADDRESS") or None
    if gpus is not None:
        local_gpus(gpus)
        if address:
            raise ConfigError(
                f"--gpus {gpus} is not accepted with a cluster ({address}): its nodes' GPUs are Ray's to place "
                "(start each node with the GPUs it offers: CUDA_VISIBLE_DEVICES=... ray start ...)"
            )
    return address


@contextlib.contextmanager
def connect(address: str | None = None, gpus: str | None = None, memory_mib: float | None = None) -> Iterator[Cluster]:
    """Joins the cluster at ``address`` (``RAY_ADDRESS`` when None), or starts Ray here over the
    local GPUs (``gpus``: the ``--gpus`` string) and stops it on leaving; ``memory_mib`` replaces the
    measured smallest GPU memory (tests)."""
    address = check_options(address, gpus)
    started = not ray.is_initialized()
    if started:
        opts = {"logging_level": logging.WARNING, "log_to_driver": False, "configure_logging": True}
        if address:
            try:
                ctx = ray.init(address=address, **opts)
            except (ConnectionError, RuntimeError, ValueError) as err:
                raise ConfigError(
                    f"no Ray cluster at {address} ({err}); accepted: the head's HOST:PORT as `ray start --head` "
                    "printed it, or no --address (and no RAY_ADDRESS) to start Ray on this machine"
                ) from err
        else:
            visible = local_gpus(gpus)
            if memory_mib is None:  # the GPUs it is started over, not every one nvidia-smi lists here
                sizes = [mib for index, mib in _smi_memory() if index in visible and mib > 0]
                memory_mib = min(sizes) if sizes else None
            env = {"CUDA_VISIBLE_DEVICES": ",".join(visible)} if visible else {}
            # Ray's notice that it turned token authentication on by default (it stays on) is not ours to print
            notice = logging.getLogger("ray._private.authentication.authentication_token_setup")
            level = notice.level
            notice.setLevel(logging.ERROR)
            try:
                with _environ(env):  # Ray hands out the GPUs it was started with
                    # "local": a Ray of its own, even where another runs on this machine (ray.init's default
                    # would join the latest one started here, /tmp/ray/ray_current_cluster)
                    ctx = ray.init(
                        address="local", num_gpus=len(visible), object_store_memory=OBJECT_STORE_BYTES, **opts
                    )
            finally:
                notice.setLevel(level)
        dashboard = getattr(ctx, "dashboard_url", None) or None
    else:
        dashboard = None
    try:
        yield _measure(address or "local", started and not address, dashboard, memory_mib)
    finally:
        if started:
            ray.shutdown()


@contextlib.contextmanager
def _environ(values: dict[str, str]) -> Iterator[None]:
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _measure(address: str, started_here: bool, dashboard: str | None, memory_mib: float | None) -> Cluster:
    """The cluster's GPUs, smallest GPU memory, fewest and most node CPUs (module docstring)."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    gpus = sum(n["Resources"].get("GPU", 0.0) for n in nodes)
    cpus = [int(n["Resources"].get("CPU", 0)) for n in nodes if n["Resources"].get("CPU", 0) >= 1]
    mib = memory_mib
    if mib is None and gpus:
        probe = ray.remote(num_cpus=0)(_node_gpu_memory)
        asks = [
            probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote()
            for n in nodes
            if n["Resources"].get("GPU", 0.0)
        ]
        sizes = [m for per_node in ray.get(asks) for m in per_node]
        mib = min(sizes) if sizes else None
    fewest, most = (min(cpus), max(cpus)) if cpus else (1, 1)
    return Cluster(address, started_here, len(nodes), gpus, mib, fewest, dashboard, most)


def _node_gpu_memory() -> list[float]:
    return [mib for _, mib in _smi_memory() if mib > 0]


# ---- what the cluster holds now (its nodes may have changed since connect measured them) ----------------


def live_nodes() -> list[dict[str, float]]:
    """Each live node's CPUs and GPUs, as Ray counts them."""
    return [
        {"CPU": n["Resources"].get("CPU", 0.0), "GPU": n["Resources"].get("GPU", 0.0)}
        for n in ray.nodes()
        if n.get("Alive")
    ]


def amount(cpus: float, gpus: float) -> str:
    return f"{cpus:g} CPU(s), {gpus:g} GPU(s)"


def check_fits(asks: dict[str, dict[str, float]]) -> None:
    """Refuses a job (its name: its task's ``num_cpus``/``num_gpus``) that no live node could ever run
    (Ray would keep it waiting, without a word)."""
    nodes = live_nodes()
    for name, ask in asks.items():
        if any(n["CPU"] >= ask["num_cpus"] and n["GPU"] >= ask["num_gpus"] for n in nodes):
            continue
        order = (lambda n: (n["GPU"], n["CPU"])) if ask["num_gpus"] else (lambda n: (n["CPU"], n["GPU"]))
        big = max(nodes, key=order) if nodes else None
        largest = f"the largest has {amount(big['CPU'], big['GPU'])}" if big else "none"
        raise ConfigError(
            f"job {name} asks for {amount(ask['num_cpus'], ask['num_gpus'])}, more than any live node of the "
            f"cluster has ({len(nodes)} alive, {largest}; the cluster changed since it was measured, or a node "
            "that could run it died): start a node that can, or run the command again to measure the cluster anew"
        )


def resources_now() -> str:
    """One line: the live nodes, the most a node has, and the free and total CPUs and GPUs."""
    nodes, free, total = live_nodes(), ray.available_resources(), ray.cluster_resources()
    most = f", at most {amount(max(n['CPU'] for n in nodes), max(n['GPU'] for n in nodes))} a node" if nodes else ""
    return (
        f"{len(nodes)} live node(s){most}; free {free.get('CPU', 0.0):g} of {total.get('CPU', 0.0):g} CPU(s), "
        f"{free.get('GPU', 0.0):g} of {total.get('GPU', 0.0):g} GPU(s)"
    )
