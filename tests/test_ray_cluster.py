"""Jobs over a Ray cluster of two nodes on this machine (``ray.cluster_utils.Cluster``: two raylets,
no GPU, one CPU each, so a job takes a whole node): the jobs spread over both nodes, and when a node
dies its job runs again on the other from where it stopped, while a finished job never runs again.
The quick test runs resumable stand-in jobs through :func:`run_jobs`; the slow one runs a real
``python -m regrasp_mjx.sweep`` of two points with ``--address``. With nodes of one and two CPUs, a
job takes the larger node whole (one at a time), and is refused once that node has died."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from regrasp_mjx.core.cluster import OBJECT_STORE_BYTES, connect
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.jobs import Job, run_jobs

# a dead node is noticed in about a second instead of Ray's default half a minute
FAST_HEALTH = {"health_check_period_ms": 200, "health_check_failure_threshold": 3, "health_check_timeout_ms": 500}


@pytest.fixture
def two_nodes():
    with _two_nodes(head_cpus=1, worker_cpus=1) as nodes:
        yield nodes


@contextlib.contextmanager
def _two_nodes(head_cpus: int, worker_cpus: int):
    import ray
    from ray.cluster_utils import Cluster

    head = {"num_cpus": head_cpus, "object_store_memory": OBJECT_STORE_BYTES, "_system_config": FAST_HEALTH}
    cluster = Cluster(initialize_head=True, head_node_args=head)
    worker = cluster.add_node(num_cpus=worker_cpus, object_store_memory=OBJECT_STORE_BYTES)
    cluster.wait_for_nodes()
    try:
        yield cluster, worker
    finally:
        ray.shutdown()
        cluster.shutdown()


def _counting_job(tmp_path: Path, name: str, steps: int) -> Job:
    """A job that counts to ``steps`` (0.2 s a step), keeping its count in a file as a checkpoint:
    started again, it goes on from the count; each start appends ``start <count> <pid>`` to its record."""
    count, record, done = tmp_path / f"{name}.count", tmp_path / f"{name}.starts", tmp_path / f"{name}.done"
    script = (
        "import os, time\n"
        f"count, record = {str(count)!r}, {str(record)!r}\n"
        "k = int(open(count).read()) if os.path.exists(count) else 0\n"
        "open(record, 'a').write(f'start {k} {os.getpid()}\\n')\n"
        f"while k < {steps}:\n"
        "    time.sleep(0.2); k += 1\n"
        "    open(count + '.tmp', 'w').write(str(k)); os.replace(count + '.tmp', count)\n"
        f"open({str(done)!r}, 'w').write('done')\n"
    )
    return Job(name, "points", lambda: ["-c", script], done, tmp_path / "logs" / f"{name}.txt")


def test_jobs_spread_over_two_nodes_and_a_dead_node_s_job_resumes_on_the_other(tmp_path, two_nodes):
    import ray

    cluster, worker = two_nodes
    ray.init(address=cluster.address, log_to_driver=False)
    jobs = [_counting_job(tmp_path, "a", 15), _counting_job(tmp_path, "b", 60)]
    nodes: dict[str, str] = {}
    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(line)
        if line.startswith("started "):
            nodes[line.split()[1]] = line.split("on node ")[1].split(",")[0]

    def kill_the_worker_node() -> None:  # once the job on the worker node has counted a while
        deadline = time.time() + 120
        while time.time() < deadline:
            on_worker = [n for n, node in nodes.items() if worker.node_id.startswith(node)]
            count = tmp_path / f"{on_worker[0]}.count" if on_worker else None
            if count is not None and count.is_file() and int(count.read_text() or 0) >= 5:
                cluster.remove_node(worker, allow_graceful=False)
                return
            time.sleep(0.1)

    killer = threading.Thread(target=kill_the_worker_node)
    killer.start()
    with connect() as c:
        assert c.nodes == 2 and c.gpus == 0 and c.node_cpus == 1
        out = run_jobs(jobs, c, log, heartbeat_s=1e9)
    killer.join()
    assert all(j.done() for j in jobs) and all(r["exit"] == 0 for r in out.values()), lines
    first_nodes = {line.split()[1]: line.split("on node ")[1].split(",")[0] for line in lines[1:3]}
    assert len(set(first_nodes.values())) == 2, lines  # one job per node, side by side
    killed = next(n for n, node in first_nodes.items() if worker.node_id.startswith(node))
    kept = ({"a", "b"} - {killed}).pop()
    starts = [line.split() for line in (tmp_path / f"{killed}.starts").read_text().splitlines()]
    assert len(starts) == 2 and starts[0][1] == "0" and int(starts[1][1]) >= 5, starts  # resumed, not anew
    assert len((tmp_path / f"{kept}.starts").read_text().splitlines()) == 1  # the other ran once
    assert not Path(f"/proc/{starts[0][2]}").is_dir()  # the dead node's process went with it
    assert int((tmp_path / f"{killed}.count").read_text()) == {"a": 15, "b": 60}[killed]
    # started again: both finished, nothing runs
    again = []
    with connect() as c:
        assert run_jobs(jobs, c, again.append, heartbeat_s=1e9) == {}
    assert again[0].startswith("2 jobs: 2 finished already, 0 to run")


def test_without_gpus_a_job_takes_the_largest_node_whole_and_is_refused_once_it_is_gone(tmp_path):
    """A job without GPUs uses every core its process sees: on a cluster of a 1-CPU head and a 2-CPU
    worker it asks for 2 CPUs, so it runs on the worker only, one job at a time (asking for the
    smallest node's CPUs, two ran on the worker at once); with the worker dead it is refused at once,
    not left to wait for a node that cannot come."""
    import ray

    with _two_nodes(head_cpus=1, worker_cpus=2) as (cluster, worker):
        ray.init(address=cluster.address, log_to_driver=False)
        jobs = [_counting_job(tmp_path, n, 5) for n in "abc"]
        lines: list[str] = []
        with connect() as c:
            assert (c.nodes, c.node_cpus, c.most_cpus) == (2, 1, 2)
            assert c.describe().endswith("2 node(s), no GPU, 2 CPU(s) per job")
            out = run_jobs(jobs, c, lines.append, heartbeat_s=1e9)
            assert all(r["exit"] == 0 for r in out.values()), lines
            assert {r["node"] for r in out.values()} == {worker.node_id[:8]}, lines
            # each process's start (its first record) and end (its finish file), by the one clock of this machine
            spans = sorted(
                (os.path.getmtime(tmp_path / f"{j.name}.starts"), os.path.getmtime(j.finished)) for j in jobs
            )
            assert all(later[0] >= earlier[1] for earlier, later in zip(spans, spans[1:])), spans  # in turn
            cluster.remove_node(worker, allow_graceful=False)
            deadline = time.time() + 60
            while time.time() < deadline and sum(n["Alive"] for n in ray.nodes()) > 1:
                time.sleep(0.2)
            late = _counting_job(tmp_path, "late", 1)
            t0 = time.perf_counter()
            with pytest.raises(
                ConfigError,
                match=r"job late asks for 2 CPU\(s\), 0 GPU\(s\), more than any live node .*"
                r"\(1 alive, the largest has 1 CPU\(s\), 0 GPU\(s\);",
            ):
                run_jobs([late], c, lines.append, heartbeat_s=1e9)
            assert time.perf_counter() - t0 < 10.0


# two smoke points train side by side on two busy cores, one of them twice (killed, then resumed)
@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_sweep_over_two_ray_nodes_finishes_every_point_after_a_node_dies(tmp_path, two_nodes):
    cluster, worker = two_nodes
    out = tmp_path / "sweep"
    argv = [sys.executable, "-m", "regrasp_mjx.sweep", "--out", str(out), "--preset", "smoke", "--seeds", "1"]
    argv += ["--set", "epochs=4", "--grid", "lr_actor=0.001|0.002", "--address", cluster.address]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("RAY_ADDRESS", None)
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    seen: list[str] = []
    reader = threading.Thread(target=lambda: seen.extend(proc.stdout))
    reader.start()
    killed = None
    deadline = time.time() + 1500
    while killed is None and time.time() < deadline and proc.poll() is None:
        for line in list(seen):
            if line.startswith("started ") and worker.node_id.startswith(line.split("on node ")[1].split(",")[0]):
                point = out / line.split()[1]
                if (point / "checkpoint" / "meta.json").is_file():  # a checkpoint to resume from: the node dies
                    cluster.remove_node(worker, allow_graceful=False)
                    killed = point
        time.sleep(0.5)
    proc.wait(timeout=1500)
    reader.join()
    text = "".join(seen)
    assert killed is not None and proc.returncode == 0, text
    record = json.loads((out / "sweep.json").read_text())
    assert all(code == 0 for code in record["exit_codes"].values()) and len(record["exit_codes"]) == 2, text
    for name in record["points"]:
        assert (out / name / "final_eval.json").is_file()
        starts = (out / name / "sweep_stdout.txt").read_text().count("started on node")
        assert starts == (2 if out / name == killed else 1), text
    # the killed point's second start resumed from its checkpoint: it did not train from scratch again
    log = (out / killed.name / "sweep_stdout.txt").read_text()
    first, second = (part.splitlines()[0] for part in log.split("started on node")[1:])
    assert "--resume" not in first and second.endswith(" --resume"), log[-3000:]
