"""Recipes as data and as one command: where a --set goes, the jobs a recipe makes, the scheduler's
needs and memory shares, the export, the docs' copy, and the smoke recipe built on the CPU end to
end, killed mid-way and resumed."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from regrasp_mjx import recipe as recipe_cli
from regrasp_mjx.core import host_loop
from regrasp_mjx.core.cluster import OBJECT_STORE_BYTES, REFERENCE_MIB, connect
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.jobs import Job, JobsStopped, run_jobs
from regrasp_mjx.inference import robustness
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.policy_file import resolve
from regrasp_mjx.inference.selection import parse_noises, score
from regrasp_mjx.planning.episodes import DemosError, check_made_for
from regrasp_mjx.workflows import recipes
from regrasp_mjx.workflows.recipes import RECIPES

ROOT = Path(__file__).resolve().parents[1]


def test_a_set_reaches_every_stage_that_has_its_key_and_a_prefixed_one_only_its_stage():
    r = RECIPES["student_v3"]
    routed = recipes.route(
        r, {"obs_noise_mm": 0.3, "env.scene.needle_radius_mm": 4.0, "teachers.hidden": (64,), "iterations": 5}
    )
    assert routed["teachers"] == {"obs_noise_mm": 0.3, "env.scene.needle_radius_mm": 4.0, "hidden": (64,)}
    assert routed["students"] == {"obs_noise_mm": 0.3, "iterations": 5}
    # the user's value wins over the recipe's own, in every variant
    assert r.student_config("t07n075", routed["students"]).obs_noise_mm == 0.3
    assert r.student_config("t07n075", {}).obs_noise_mm == 0.75
    assert r.teacher_config(routed["teachers"]).env.scene.needle_radius_mm == 4.0
    with pytest.raises(ConfigError, match="no stage of recipe student_v3 has 'colour'"):
        recipes.route(r, {"colour": 1})
    with pytest.raises(ConfigError, match="recipe general has no students"):
        recipes.route(RECIPES["general"], {"students.iterations": 3})
    with pytest.raises(ConfigError, match="epochs"):  # every stage's config is made before anything runs
        recipes.check(r, {"epochs": -1})


def test_a_students_recipe_makes_the_documented_jobs(tmp_path):
    plan = recipe_cli.Plan(RECIPES["student_v3"], tmp_path, ["env.scene.needle_radius_mm=4.0", "iterations=5"], 3)
    jobs = {j.name: j for j in plan.jobs()}
    students = [n for n in jobs if n.startswith("students/")]
    assert students == [f"students/{v}/s{s}" for v in ("t07", "t07n075") for s in range(3)]
    assert [n for n in jobs if n.startswith("select/")] == [
        f"select/{v}_s{s}" for v in ("t07", "t07n075") for s in range(3)
    ]
    assert jobs["teachers"].needs == ("demos",) and jobs["choose"].needs == tuple(
        f"select/{n}" for n in plan.candidates()
    )
    demos = jobs["demos"].argv()
    assert demos[demos.index("--n") + 1] == "9900" and "scene.needle_radius_mm=4.0" in demos
    assert demos[demos.index("--workers") + 1] == "3"
    train = jobs["teachers"].argv()
    assert train[train.index("--preset") + 1] == "decay" and "env.scene.needle_radius_mm=4.0" in train
    s = jobs["students/t07n075/s2"].argv()
    assert s[s.index("--teacher") + 1] == str(tmp_path / "teachers" / "seed2" / "policy")
    # the variant's noise, then the user's iterations last (the last --set of a key wins)
    sets = [s[i + 1] for i, x in enumerate(s) if x == "--set"]
    assert sets.index("obs_noise_mm=0.75") < sets.index("iterations=5") == len(sets) - 1
    assert "iterations=20" in sets
    sel = jobs["select/t07_s0"].argv()
    assert sel[sel.index("--heldout") + 1] == "1000:7000001" and "--no-testset" in sel  # never a test set
    # without a GPU the report is one job; on GPUs it is parts side by side, one compiled program
    # each, that hold exactly the whole table's rows (in its order once joined), and a job joining them
    assert jobs["report"].needs == ("choose",) and not any(n.startswith("report/") for n in jobs)
    on_gpus = {j.name: j for j in recipe_cli.Plan(RECIPES["student_v3"], tmp_path, [], 3, gpus=True).jobs()}
    parts = [n for n in on_gpus if n.startswith("report/")]
    assert len(parts) == 15 and on_gpus["report"].needs == tuple(parts)
    rows = []
    for name in parts:
        argv = on_gpus[name].argv()
        assert on_gpus[name].needs == ("choose",) and on_gpus[name].share * len(parts) <= 0.6 + 1e-9
        (mode,) = argv[argv.index("--modes") + 1].split(",")
        rows += [(c, mode) for c in argv[argv.index("--conditions") + 1].split(",")]
    whole = [
        (c.name, m) for c in robustness.ALL_CONDITIONS for m in robustness.MODES if c.modes is None or m in c.modes
    ]
    order = {c: i for i, (c, _) in enumerate(whole)}
    assert sorted(rows, key=lambda r: order[r[0]]) == whole  # merge's stable sort by condition
    merge = on_gpus["report"].argv()
    assert merge[merge.index("--merge") + 1 : merge.index("--out")] == [str(on_gpus[n].finished) for n in parts]
    # a general recipe's candidates are its teacher seeds
    general = recipe_cli.Plan(RECIPES["general"], tmp_path / "g", [], 1)
    assert list(general.candidates()) == ["teacher_s0", "teacher_s1", "teacher_s2"]
    assert (
        "--task" in (d := {j.name: j for j in general.jobs()}["demos"].argv()) and d[d.index("--task") + 1] == "general"
    )


def test_on_gpus_precompile_jobs_run_each_later_stage_s_programs_on_untrained_networks(tmp_path):
    """Each precompile job runs the command of the jobs it helps with an untrained network of the
    same shape (so the same compiled programs; tests/test_recipe.py's slow check shows they are),
    shares their programs key; the distillations start beside the teachers, the rest beside the
    students (a generalist's, without students, beside the teachers); without a GPU there are none."""
    plan = recipe_cli.Plan(RECIPES["student_v3"], tmp_path, ["iterations=5"], 3, gpus=True)
    jobs = {j.name: j for j in plan.jobs()}
    pre = [n for n in jobs if n.startswith("precompile/")]
    assert pre[:3] == ["precompile/students/t07", "precompile/students/t07n075", "precompile/select"]
    assert len(pre) == 3 + 15 and list(jobs)[:2] == ["demos", "teachers"]  # the teachers start first
    untrained = str(tmp_path / "precompile" / "teacher")
    for variant in ("t07", "t07n075"):
        job, real = jobs[f"precompile/students/{variant}"], jobs[f"students/{variant}/s0"]
        argv, want = job.argv(), real.argv()
        assert argv[argv.index("--teacher") + 1] == untrained and "--precompile" in argv
        assert [a for a in argv if a.startswith(("hidden", "iterations", "obs_"))] == [
            a for a in want if a.startswith(("hidden", "iterations", "obs_"))
        ]
        assert (job.programs, job.compiled, job.share) == (real.programs, real.compiled, real.share)
        assert job.helps == tuple(f"students/{variant}/s{s}" for s in range(3)) and job.needs == ("demos",)
    sel, real = jobs["precompile/select"], jobs["select/t07_s0"]
    strip = lambda a: [x for x in a[a.index("--heldout") : a.index("--out")]]  # noqa: E731
    assert strip(sel.argv()) == strip(real.argv()) and sel.programs == real.programs == "select"
    assert sel.argv()[sel.argv().index("--policy") + 1] == f"untrained={tmp_path / 'precompile/student'}"
    assert sel.needs == ("teachers",) and set(sel.helps) == {n for n in jobs if n.startswith("select/")}
    for i in range(15):
        job, real = jobs[f"precompile/report/{i:02d}"], jobs[f"report/part{i:02d}"]
        a, b = job.argv(), real.argv()
        assert a[a.index("--modes") : a.index("--out")] == b[b.index("--modes") : b.index("--out")]
        assert job.programs == real.programs and job.helps == (real.name,) and job.share == real.share
        assert job.needs == ("teachers",)
    # the untrained networks are written before the jobs start, with the teachers' and the students'
    # shapes and the teachers' task (as distill exports a student), numpy only
    plan.prepare()
    teacher, student = load_policy(untrained), load_policy(tmp_path / "precompile" / "student")
    assert teacher.hidden == plan.teacher_cfg.hidden and teacher.contract["training"]["untrained"] is True
    assert student.hidden == (256, 256) and student.env_config == teacher.env_config == plan.teacher_cfg.env
    # a generalist's candidates are teachers: its selection and report precompile on the untrained teacher
    general = {j.name: j for j in recipe_cli.Plan(RECIPES["general"], tmp_path / "g", [], 3, gpus=True).jobs()}
    g = general["precompile/select"]
    assert g.needs == ("demos",) and f"untrained={tmp_path / 'g/precompile/teacher'}" in g.argv()
    assert not any(n.startswith("precompile/students") for n in general)
    assert not any(j.stage == "precompile" for j in recipe_cli.Plan(RECIPES["student_v3"], tmp_path, [], 3).jobs())


def test_the_jaws40_recipe_trains_jaws_that_open_and_chooses_under_a_camera_s_errors(tmp_path):
    """A candidate default (issue 67): teachers whose jaws open on the way, three student variants (one
    aiming inside half the tolerances), candidates scored on the camera rows too, the closed loop's
    looking chosen with its stop; the report's programs are not precompiled (they run the chosen loop)."""
    r = RECIPES["jaws40"]
    assert r.teacher_config().env.jaw_open_deg == 40
    assert r.student_config("t05").goal_tolerance == 0.5 and r.student_config("t07").goal_tolerance == 0.7
    plan = recipe_cli.Plan(r, tmp_path, [], 3, gpus=True)
    jobs = {j.name: j for j in plan.jobs()}
    assert [n for n in jobs if n.startswith("students/")] == [
        f"students/{v}/s{s}" for v in ("t07", "t05", "t07n075") for s in range(3)
    ]
    # a share is of an 80 GB GPU: a distillation whose jaws open held 9.8 GB on an H200 (0.1 ran out)
    assert all(jobs[f"students/{v}/s0"].share * 80 >= 9.8 for v in ("t07", "t05", "t07n075"))
    # the teacher seeds are candidates after the students (of equal scores the smaller network wins),
    # their selection a program set of their own (another network's shape)
    assert list(plan.candidates())[-3:] == ["teacher_s0", "teacher_s1", "teacher_s2"] and len(plan.candidates()) == 12
    assert jobs["select/teacher_s2"].needs == ("teachers",) and jobs["select/teacher_s2"].programs == "select/teachers"
    assert jobs["select/t05_s1"].programs == "select" and len(jobs["choose"].needs) == 12
    sel = jobs["select/t05_s1"].argv()
    wanted = sel[sel.index("--conditions") + 1].split(",")
    assert "camera: lab-good" in wanted and set(wanted) == {c for _, c in r.selection.rule}
    names = {c.name for c in robustness.ALL_CONDITIONS}
    assert set(wanted) <= names  # every row the score needs is one the table has
    assert not any(n.startswith("precompile/report") for n in jobs) and "precompile/select" in jobs
    assert r.selection.loop_looks == (0, 60) and len(parse_noises(r.selection.loop_noises)) == 4


def test_the_default_recipe_ships_its_best_teacher_and_precompiles_the_report_of_its_looking_loop(tmp_path):
    """Issue 67: the default's jaws open on the way, its candidates are its teacher seeds (no students),
    scored under a camera's errors; its loop looks (one look budget, one warm-up), so the report's
    programs are precompiled beside the teachers on an untrained teacher whose file names them."""
    r = RECIPES["default"]
    assert r.students is None and r.teacher_config().env.jaw_open_deg == 40
    assert r.selection.loop_looks == (60,) and r.selection.loop_warmups == (10,)
    plan = recipe_cli.Plan(r, tmp_path, [], 3, gpus=True)
    jobs = {j.name: j for j in plan.jobs()}
    assert list(plan.candidates()) == ["teacher_s0", "teacher_s1", "teacher_s2"]
    reports = [n for n in jobs if n.startswith("precompile/report/")]
    assert len(reports) == 15 and all(jobs[n].needs == ("demos",) for n in reports)  # beside the teachers
    report = str(tmp_path / "precompile" / "report_candidate")
    assert all(jobs[n].argv()[jobs[n].argv().index("--policy") + 1] == f"untrained={report}" for n in reports)
    plan.prepare()
    candidate = load_policy(report)
    assert candidate.hidden == plan.teacher_cfg.hidden and candidate.env_config.jaw_open_deg == 40
    assert candidate.closed_loop_defaults["look_frames"] == 60 and candidate.closed_loop_defaults["warmup_frames"] == 10
    assert candidate.closed_loop_defaults["jaw_sigmas"] == 0.0  # the exported policy's margin too
    # a recipe that chooses among look budgets cannot know the report's programs before it chooses
    assert not any(
        n.startswith("precompile/report")
        for n in (j.name for j in recipe_cli.Plan(RECIPES["jaws40"], tmp_path / "j", [], 3, gpus=True).jobs())
    )


@contextlib.contextmanager
def _ray(gpus: int, cpus: int = 4, memory_mib: float | None = None):
    """A Ray of its own on this machine with ``gpus`` GPUs as Ray counts them (none need exist: Ray
    hands out their indices in CUDA_VISIBLE_DEVICES), as ``connect`` sees it."""
    import ray

    # "local": its own, not the Ray of another test running beside it on this machine
    ray.init("local", num_cpus=cpus, num_gpus=gpus, object_store_memory=OBJECT_STORE_BYTES, log_to_driver=False)
    try:
        with connect(memory_mib=memory_mib) as cluster:
            yield cluster
    finally:
        ray.shutdown()


def test_a_helper_job_fails_nothing_and_is_not_run_once_what_it_helps_has_finished(tmp_path):
    helper = dataclasses.replace(_job(tmp_path, "h", 0.1, code=1, seconds=1.5), helps=("w",), programs="p")
    first = _job(tmp_path, "x", 0.1, seconds=0.3)  # w is ready while h still runs
    real = dataclasses.replace(_job(tmp_path, "w", 0.1, needs=("x",)), programs="p")
    lines, spared = [], []
    with _ray(gpus=1) as cluster:
        out = run_jobs([helper, first, real], cluster, lines.append, heartbeat_s=1e9)
        assert out["h"]["exit"] == 1 and out["w"]["exit"] == 0 and real.done()
        assert any("h FAILED" in x and "the jobs it helps compile their own programs" in x for x in lines)
        assert lines.index(next(x for x in lines if x.startswith("started w"))) > lines.index(
            next(x for x in lines if x.startswith("h FAILED"))
        )  # w shares h's programs: it waited for h to compile them (here: to end)
        assert run_jobs([helper, first, real], cluster, spared.append, heartbeat_s=1e9) == {}  # w finished
    assert spared[0].startswith("3 jobs: 2 finished already, 1 no longer needed")


def test_helpers_yield_to_the_jobs_that_do_the_work_and_shares_are_of_an_80_gb_gpu(tmp_path, monkeypatch):
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    # a and b do not fit side by side; the helper h (listed first, and small enough to fit beside
    # either) waits until both have started, then starts while c, which it helps, is still to
    # start; g's helped job has started by the time g could: g is not run
    a, b = _job(tmp_path, "a", 0.6, seconds=1.5), _job(tmp_path, "b", 0.6, seconds=1.5)
    c = _job(tmp_path, "c", 0.1, needs=("b",))
    h = dataclasses.replace(_job(tmp_path, "h", 0.1), helps=("c",))
    g = dataclasses.replace(_job(tmp_path, "g", 0.1, needs=("a",)), helps=("quick",))
    quick = _job(tmp_path, "quick", 0.1)
    lines = []
    with _ray(gpus=1) as cluster:
        out = run_jobs([h, g, a, b, c, quick], cluster, lines.append, heartbeat_s=1e9)
    t = {j.name: [float(x) for x in j.finished.read_text().split()[:2]] for j in (a, b, c, h)}
    first, second = sorted("ab", key=lambda n: t[n][0])
    assert t[second][0] >= t[first][1]  # a's and b's shares with their contexts exceed the GPU
    # h ran, and only once both had started: after the first ended (the second's task starts only then; its
    # process's own clock reading comes a few milliseconds after h's may, and whether h's process starts before
    # c's depends on how fast a fresh Ray worker imports the package on a busy machine)
    assert h.done() and t[first][1] <= t["h"][0]
    assert not g.done() and "g" not in out and "g not started: the jobs it helps have started" in lines
    # on a GPU of twice the memory the same shares fit side by side, each with half the fraction
    big = [_job(tmp_path / "big", n, 0.6, seconds=1.5) for n in "pq"]
    whole = _job(tmp_path / "whole", "w", 1.0)  # a whole GPU (a sweep's point, share 1) stays a whole GPU on any
    lines = []
    with _ray(gpus=1, memory_mib=2 * REFERENCE_MIB) as cluster:
        run_jobs(big, cluster, lines.append, heartbeat_s=1e9)
        run_jobs([whole], cluster, lambda _: None, heartbeat_s=1e9)
    p, q = (j.finished.read_text().split() for j in big)
    assert max(float(p[0]), float(q[0])) < min(float(p[1]), float(q[1])) and p[3] == q[3] == "0.300"
    assert any(x.startswith("started p on node ") and x.endswith("GPU 0, 30% of its memory") for x in lines)
    assert whole.finished.read_text().split()[3] == "0.950"


def _job(tmp_path, name, share, needs=(), code=0, seconds=0.6, together=()):
    """A job that records when it ran and which GPU it was given, then exits with ``code``; with
    ``together``, it first waits (a minute at most, else exit 5) until those jobs have all begun
    too: it finishes only if they ran side by side (not a matter of timing on a busy machine)."""
    done = tmp_path / f"{name}.done"
    wait = ""
    if together:
        marks = [str(tmp_path / f"{n}.began") for n in together]
        wait = (
            f"open({str(tmp_path / f'{name}.began')!r}, 'w').close(); "
            f"[time.sleep(0.1) for _ in range(600) if not all(os.path.exists(m) for m in {marks!r})]; "
            f"sys.exit(5) if not all(os.path.exists(m) for m in {marks!r}) else None; "
        )
    script = (
        f"import os, sys, time; t0 = time.time(); {wait}time.sleep({seconds}); "
        f"open({str(done)!r}, 'w').write(f\"{{t0}} {{time.time()}} {{os.environ.get('CUDA_VISIBLE_DEVICES')}} "
        f"{{os.environ.get('XLA_PYTHON_CLIENT_MEM_FRACTION')}} {{os.environ.get('JAX_PLATFORMS')}} "
        f"{{os.environ.get('XLA_CLIENT_MEM_FRACTION')}} {{os.environ.get('OMP_NUM_THREADS')}}\") "
        f"if {code} == 0 else None; sys.exit({code})"
    )
    return Job(name, "stage", lambda: ["-c", script], done, tmp_path / "logs" / f"{name}.txt", share, needs)


def test_the_scheduler_keeps_needs_and_memory_shares_and_skips_what_finished(tmp_path, monkeypatch):
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)  # another test's process may have set it
    monkeypatch.setenv("XLA_CLIENT_MEM_FRACTION", "0.5")  # a user's, in the environment Ray's workers inherit
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)  # Ray sets it in its workers: the jobs must not inherit it
    jobs = [
        # two fill one GPU under half each, the third runs on the other: all three side by side
        *(_job(tmp_path, n, 0.45, together="abc") for n in "abc"),
        _job(tmp_path, "d", 0.9, needs=("a", "b", "c")),
        _job(tmp_path, "e", 0.1, needs=("d",), code=3),
        _job(tmp_path, "f", 0.1, needs=("e",)),
    ]
    lines, again, spared = [], [], []
    made = _job(tmp_path, "made", 0.1)
    uses = _job(tmp_path, "uses", 0.1, needs=("made",))
    uses.finished.write_text("done earlier")
    halves = [_job(tmp_path / "halves", n, 0.5) for n in "pq"]
    with _ray(gpus=2) as cluster:
        out = run_jobs(jobs, cluster, lines.append, heartbeat_s=1e9)
        ran = {j.name: j.finished.read_text().split() for j in jobs if j.done()}
        # started again: the finished ones are skipped, the failed one runs again
        out_again = run_jobs(jobs, cluster, again.append, heartbeat_s=1e9)
        # a job whose dependents have all finished is not run again (demonstrations deleted after training)
        assert run_jobs([made, uses], cluster, spared.append, heartbeat_s=1e9) == {}
    with _ray(gpus=1) as cluster:  # each process's CUDA context counts too: two halves do not fit on one GPU
        run_jobs(halves, cluster, lambda _: None, heartbeat_s=1e9)
    assert set(ran) == {"a", "b", "c", "d"}
    start, end = {n: float(v[0]) for n, v in ran.items()}, {n: float(v[1]) for n, v in ran.items()}
    assert start["d"] >= max(end["a"], end["b"], end["c"])  # its needs first
    assert ran["d"][3] == "0.900" and {ran[n][2] for n in "abc"} == {"0", "1"}
    assert ran["d"][5] == "None"  # one spelling of the fraction: both make JAX's CUDA plugin fall back to the CPU
    assert ran["d"][6] == "None"  # not Ray's OMP_NUM_THREADS=1 (a GPU job's task asks no CPU)
    assert out["e"]["exit"] == 3 and out["f"]["exit"] is None  # a failed need: never started
    assert any("f not started: a job it needs failed" in x for x in lines)
    assert set(out_again) == {"e", "f"} and again[0].startswith("6 jobs: 4 finished already, 2 to run on Ray")
    assert spared[0].startswith("2 jobs: 1 finished already, 1 no longer needed") and not made.done()
    p, q = (j.finished.read_text().split() for j in halves)
    assert min(float(p[0]), float(q[0])) + 0.6 <= max(float(p[0]), float(q[0]))  # in turn
    # no GPU: one job per node at a time (a job takes the node's CPUs), told to use the CPU
    cpu = [_job(tmp_path / "cpu", n, 0.1) for n in "xy"]
    with _ray(gpus=0, cpus=2) as cluster:
        assert cluster.describe().endswith("1 node(s), no GPU, 2 CPU(s) per job")
        run_jobs(cpu, cluster, lambda _: None, heartbeat_s=1e9)
    x, y = (j.finished.read_text().split() for j in cpu)
    assert min(float(x[1]), float(y[1])) <= max(float(x[0]), float(y[0]))  # one after the other
    assert x[3] == "None" and x[4] == "cpu"


def test_jobs_of_one_program_set_wait_for_the_first_to_compile(tmp_path):
    """The first job of a ``programs`` key runs alone until its log shows ``compiled`` (then the
    others start beside it); a key whose first job prints nothing waits for it to end."""

    def job(name, programs, compiled, seconds, wait_for=()):
        done, began = tmp_path / f"{name}.done", tmp_path / f"{name}.began"
        marks = [str(tmp_path / f"{n}.began") for n in wait_for]
        script = (
            f"import os, time, sys; t0 = time.time(); open({str(began)!r}, 'w').close(); time.sleep(0.5); "
            "t1 = time.time(); print('distill 2/20', flush=True); "
            # the first waits (a minute at most, else exit 5) for the others to begin: it finishes only
            # if they started beside it, whatever the machine's load
            f"[time.sleep(0.1) for _ in range(600) if not all(os.path.exists(m) for m in {marks!r})]; "
            f"sys.exit(5) if not all(os.path.exists(m) for m in {marks!r}) else None; "
            f"time.sleep({seconds}); open({str(done)!r}, 'w').write(f'{{t0}} {{time.time()}} {{t1}}')"
        )
        log = tmp_path / "logs" / f"{name}.txt"
        return Job(name, "students", lambda: ["-c", script], done, log, 0.1, (), programs, compiled)

    jobs = [job("s0", "a", "distill 2/20", 0.5, wait_for=("s1", "s2"))]
    jobs += [job(f"s{i}", "a", "distill 2/20", 0.5) for i in (1, 2)]
    jobs += [job(f"q{i}", "b", None, 1.0) for i in range(2)]
    lines = []
    with _ray(gpus=1) as cluster:
        out = run_jobs(jobs, cluster, lines.append, heartbeat_s=1e9)
    assert all(r["exit"] == 0 for r in out.values()), lines  # s0 saw s1 and s2 begin beside it
    t = {j.name: [float(x) for x in j.finished.read_text().split()] for j in jobs}
    assert all(t[n][0] >= t["s0"][2] for n in ("s1", "s2"))  # after s0 printed its line
    assert t["q1"][0] >= t["q0"][1]  # b never printed its marker: its second job waited for the first to end
    assert t["q0"][0] < t["s0"][1]  # another key does not wait for this one
    assert any("s0 has compiled its programs" in x for x in lines)


def test_ctrl_c_stops_the_running_jobs_processes_and_says_which(tmp_path):
    """A KeyboardInterrupt while jobs run cancels their tasks; their processes end with them (no
    job runs on without its task); the record says which were stopped."""
    pid_file = tmp_path / "pid"
    script = f"import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(120)"
    slow = Job("slow", "stage", lambda: ["-c", script], tmp_path / "slow.done", tmp_path / "slow.txt", 0.1)
    after = _job(tmp_path, "after", 0.1, needs=("slow",))
    records = []

    def interrupt(line: str) -> None:
        if line.startswith("started slow"):  # its task has begun; Ctrl-C once its process runs
            deadline = time.time() + 60
            while not pid_file.is_file() and time.time() < deadline:
                time.sleep(0.1)
            raise KeyboardInterrupt

    with _ray(gpus=1) as cluster:
        with pytest.raises(JobsStopped, match=r"stopped 1 running job\(s\) \(slow\)"):
            run_jobs([slow, after], cluster, interrupt, heartbeat_s=1e9, on_end=lambda out: records.append(out))
    deadline = time.time() + 30
    while time.time() < deadline and _alive(int(pid_file.read_text())):
        time.sleep(0.2)
    assert not _alive(int(pid_file.read_text())), "the stopped job's process runs on"
    assert records[-1]["slow"]["exit"] == "stopped" and not after.done()


def test_a_sigterm_that_python_would_drop_in_a_gc_callback_still_stops_the_jobs(tmp_path):
    """A SIGTERM (SLURM's time limit, scancel) that lands inside a garbage-collector callback (as
    XLA's ``_xla_gc_callback`` runs), where Python drops the KeyboardInterrupt it raises, still stops
    the jobs: it is raised again a moment later, as Ctrl-C is."""
    import gc

    pid_file = tmp_path / "pid"
    script = f"import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(60)"
    slow = Job("slow", "stage", lambda: ["-c", script], tmp_path / "slow.done", tmp_path / "slow.txt", 0.1)
    armed = []

    def callback(phase, info):
        if phase == "start" and armed:
            armed.clear()
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between these bytecodes, inside this callback
                pass

    def terminate(line: str) -> None:
        if line.startswith("started slow"):
            deadline = time.time() + 60
            while not pid_file.is_file() and time.time() < deadline:
                time.sleep(0.1)
            armed.append(True)
            gc.collect()

    gc.callbacks.append(callback)
    # Ctrl-C's handler as run_command sets it (an interrupt raised again can land in a gc callback again)
    previous = signal.signal(signal.SIGINT, host_loop._on_sigint)
    try:
        with _ray(gpus=1) as cluster:
            t0 = time.perf_counter()
            with pytest.raises(JobsStopped, match=r"stopped 1 running job\(s\) \(slow\)"):
                run_jobs([slow], cluster, terminate, heartbeat_s=1e9)
            assert time.perf_counter() - t0 < 30.0  # not the job's minute: stopped, not run to its end
    finally:
        signal.signal(signal.SIGINT, previous)
        gc.callbacks.remove(callback)
    assert not slow.done()


def test_jobs_that_cannot_be_placed_now_are_named_with_what_they_wait_for_and_wait_on(tmp_path):
    """Pending jobs with none running (here the only GPU held by another task) print a line each
    heartbeat naming them, their ask and what the cluster has free, and wait on until it frees."""
    import ray

    whole = _job(tmp_path, "w", 1.0)
    after = _job(tmp_path, "after", 0.1, needs=("w",))
    lines = []

    class Holder:  # defined here, so Ray sends it to its worker by value (this module is not imported there)
        def ready(self) -> bool:
            return True

    def free_later(holder, seconds: float) -> None:
        time.sleep(seconds)
        ray.kill(holder)

    with _ray(gpus=1) as cluster:
        holder = ray.remote(num_gpus=1, num_cpus=0)(Holder).remote()
        ray.get(holder.ready.remote())
        # a safety net: without the lines the GPU is freed after a minute and the test fails, not hangs
        stop = ray.remote(num_cpus=0)(free_later).remote(holder, 60.0)

        def log(line: str) -> None:
            lines.append(line)
            if sum(x.startswith("no job running") for x in lines) == 2:  # said twice: freed, the job runs
                ray.kill(holder)

        out = run_jobs([whole, after], cluster, log, heartbeat_s=0.5)
        ray.cancel(stop, force=True)
    waits = [x for x in lines if x.startswith("no job running")]
    assert len(waits) >= 2, lines  # and on, while w's worker starts
    assert "waiting for Ray to place w (0 CPU(s), 1 GPU(s)) (1 more wait for the jobs they need)" in waits[0]
    assert waits[0].endswith(
        "the cluster now: 1 live node(s), at most 4 CPU(s), 1 GPU(s) a node; free 4 of 4 CPU(s), 0 of 1 GPU(s)"
    )
    assert out["w"]["exit"] == 0 and out["after"]["exit"] == 0


def test_a_job_whose_folder_is_still_locked_waits_for_the_lock_then_runs(tmp_path):
    """A job run again after its node died can find its folder's lock still held (on NFS the server
    frees it later): its process says so and exits 2; the task starts it again until the lock is free."""
    flag, done = tmp_path / "tried", tmp_path / "j.done"
    script = (
        "import os, sys\n"
        f"if not os.path.exists({str(flag)!r}):\n"
        f"    open({str(flag)!r}, 'w').close()\n"
        "    print('error: --out x is in use by another run (pid 1); accepted: another --out'); sys.exit(2)\n"
        f"open({str(done)!r}, 'w').write('done')\n"
    )
    job = Job("j", "stage", lambda: ["-c", script], done, tmp_path / "j.txt", 0.1)
    fails = Job("k", "stage", lambda: ["-c", "import sys; sys.exit(2)"], tmp_path / "k.done", tmp_path / "k.txt", 0.1)
    with _ray(gpus=1) as cluster:
        out = run_jobs([job, fails], cluster, lambda _: None, heartbeat_s=1e9)
    assert out["j"]["exit"] == 0 and job.done() and job.log.read_text().count("started on node") == 2
    assert out["k"]["exit"] == 2 and (tmp_path / "k.txt").read_text().count("started on node") == 1  # no lock: once


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").is_dir() and "zombie" not in Path(f"/proc/{pid}/status").read_text().lower()


def test_the_score_is_the_mean_success_over_the_rule_rows_and_the_best_candidate_wins():
    rows = lambda fused, per_frame: [  # noqa: E731
        {"mode": "fused", "condition": "sigma 0.25 mm", "success_rate": fused},
        {"mode": "per-frame-stop", "condition": "sigma 0.25 mm", "success_rate": per_frame},
        {"mode": "open", "condition": "exact", "success_rate": 0.0},  # not in the rule: ignored
    ]
    rule = (("fused", "sigma 0.25 mm"), ("per-frame-stop", "sigma 0.25 mm"))
    scores = {
        "a": score(rows(0.96, 0.80), rule),
        "b": score(rows(0.98, 0.80), rule),
        "c": score(rows(0.98, 0.80), rule),
    }
    assert scores == pytest.approx({"a": 0.88, "b": 0.89, "c": 0.89})
    assert max(scores, key=scores.get) == "b"  # the first of equals, as the recipe chooses
    with pytest.raises(ConfigError, match=r"lacks the rows \['fused / sigma 0.5 mm'\]"):
        score(rows(1.0, 1.0), (("fused", "sigma 0.5 mm"),))


def test_export_writes_the_closed_loop_and_the_recipe_into_a_loadable_policy(tmp_path):
    source = resolve("student_v3")  # jaws kept at the scene's opening (the default's open on the way: below)
    provenance = {"name": "smoke", "overrides": ["iterations=3"], "commit": recipe_cli.commit()}
    loop = {"stop_tolerance": 0.9, "warmup_frames": 5, "look_frames": 60}
    recipe_cli.export(source, tmp_path / "policy", loop, "validation", provenance)
    policy = load_policy(tmp_path / "policy")
    assert policy.closed_loop_defaults == {
        "stop_tolerance": 0.9,
        "warmup_frames": 5,
        "look_frames": 60,
        "jaw_deg": None,  # the jaws kept at the scene's opening
        "jaw_sigmas": 2.0,
    }
    contract = json.loads((tmp_path / "policy" / "policy.json").read_text())
    assert contract["training"]["recipe"]["overrides"] == ["iterations=3"]
    assert set(contract["training"]["recipe"]["commit"]) == {"commit", "dirty"}
    assert not (tmp_path / "policy.partial").exists()
    # a policy whose jaws open on the way keeps no margin in the view's errors unless its file names one
    recipe_cli.export(
        ROOT / "experiments/results/jaw_on_the_way/policy_open40", tmp_path / "p40", loop, "v", provenance
    )
    assert load_policy(tmp_path / "p40").closed_loop_defaults["jaw_sigmas"] == 0.0


def test_demonstrations_of_another_scene_are_refused(tmp_path):
    r = RECIPES["default"]

    class Made:
        meta = {"settings": {"env": {"scene": {"needle_radius_mm": 5.4}, "task": {"start_distance_mm": 13.0}}}}

    assert check_made_for(Made, r.teacher_config().env, tmp_path) is Made
    with pytest.raises(DemosError, match=r"another scene \(needle_radius_mm=5.4; this run: needle_radius_mm=4.0\)"):
        check_made_for(Made, r.teacher_config({"env.scene.needle_radius_mm": 4.0}).env, tmp_path)


def test_docs_show_the_recipes_as_the_data_says():
    text = (ROOT / "docs" / "training.md").read_text()
    block = text.split("<!-- recipes:begin -->\n", 1)[1].split("<!-- recipes:end -->", 1)[0]
    assert block.strip().splitlines() == recipes.render_docs(), (
        "docs/training.md's recipe block is stale: python experiments/recipe_docs.py"
    )


def _recipe(out: Path, *more: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    argv = [sys.executable, "-m", "regrasp_mjx.recipe", "smoke", "--out", str(out), "--workers", "1", *more]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, **kw)


# the suite's slowest test: every stage's process compiles its programs on two busy cores (440 s in
# CI on 2026-11-26, 608 s alone on a slower day): its own limit, above the suite's 900 s per test
@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_the_smoke_recipe_builds_on_the_cpu_and_resumes_after_a_kill(tmp_path):
    out = tmp_path / "r"
    first = _recipe(out, start_new_session=True)  # its own process group: killed whole, as by a lost machine
    seen = []
    deadline = time.time() + 1500
    for line in first.stdout:
        seen.append(line)
        if line.startswith("started students/t07/s0"):
            time.sleep(3.0)  # the student under way
            os.killpg(first.pid, signal.SIGKILL)
            break
        assert time.time() < deadline, "".join(seen)
    first.wait()
    assert (out / "teachers" / "final_eval.json").is_file() and not (out / "policy").exists(), "".join(seen)
    assert (out / "teachers" / "policy" / "policy.json").is_file()  # one teacher seed: its policy in the run folder

    again = _recipe(out)
    text = again.communicate(timeout=1500)[0]
    assert again.returncode == 0, text
    assert text.startswith("6 jobs: 2 finished already, 4 to run"), text  # demos and teachers kept
    assert "started demos" not in text and "started teachers" not in text
    policy = load_policy(out / "policy")
    contract = policy.contract
    assert contract["training"]["recipe"]["name"] == "smoke"
    assert contract["training"]["recipe"]["candidate"] == "t07_s0"
    assert contract["closed_loop"]["stop_tolerance"] in (0.8, 0.9)
    assert (out / "robustness.json").is_file() and (out / "selection.md").is_file()
    record = json.loads((out / "recipe.json").read_text())
    assert len(record["runs"]) == 2 and record["runs"][1]["jobs"]["students/t07/s0"]["exit"] == 0
    assert record["runs"][0]["jobs"]["teachers"]["exit"] == 0  # the killed call kept the times of what ended

    # the same arguments again: nothing left to run; other arguments: refused in one line
    done = _recipe(out)
    assert "6 jobs: 6 finished already, 0 to run" in done.communicate(timeout=300)[0]
    other = _recipe(out, "--set", "iterations=3")
    text = other.communicate(timeout=300)[0]
    assert other.returncode == 2 and text.strip().count("\n") == 0 and "holds recipe smoke with overrides []" in text


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_precompiled_distillation_and_candidate_leave_nothing_to_compile(tmp_path):
    """What ``recipe``'s precompile jobs rely on: a distillation and a selection candidate run on an
    untrained network of the teacher's shape compile every program that the real ones (another
    teacher, another seed) then run: the real ones add nothing to the compilation cache."""
    from regrasp_mjx.agents.ddpg_bc.config import make_config
    from regrasp_mjx.inference.policy_file import untrained_policy

    cfg = make_config("smoke")
    for seed in (0, 1):
        untrained_policy(tmp_path / f"t{seed}", cfg.hidden, cfg.env, seed=seed)
    smoke = RECIPES["smoke"].students
    sets = [x for k, v in (*smoke.settings, *smoke.variants[0][1]) for x in ("--set", f"{k}={v!r}".replace(" ", ""))]
    # every program cached, however fast it compiled: at JAX's default (1 s) a small program that
    # compiled in 0.9 s in one run and 1.1 s in the other (a loaded machine) was written only once
    env = {**os.environ, "REGRASP_JAX_CACHE": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu"}
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    env.pop("JAX_COMPILATION_CACHE_DIR", None)

    def run(*argv):
        done = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, env=env, cwd=ROOT)
        assert done.returncode == 0, done.stdout + done.stderr
        return sorted(os.listdir(tmp_path / "cache"))

    distill = ["regrasp_mjx.distill", "--testset", "paper300", *sets]
    warm = run(*distill, "--teacher", str(tmp_path / "t0"), "--out", str(tmp_path / "w"), "--precompile")
    assert (tmp_path / "w" / "precompile.json").is_file() and not (tmp_path / "w" / "distill_eval.json").exists()
    assert len(warm) >= 4  # the iteration, the evaluations, the test set's plans
    real = run(*distill, "--teacher", str(tmp_path / "t1"), "--out", str(tmp_path / "r"), "--seed", "1")
    assert real == warm and (tmp_path / "r" / "distill_eval.json").is_file()
    compare = ["regrasp_mjx.compare", "--robustness", "--heldout", "20:7", "--no-testset", "--modes", "fused"]
    compare += ["--conditions", "sigma 0.25 mm", "--out", str(tmp_path / "sel")]
    warm = run(*compare, "--policy", f"u={tmp_path / 'w' / 'policy'}", "--name", "u")
    assert len(warm) > len(real)
    assert run(*compare, "--policy", f"s={tmp_path / 'r' / 'policy'}", "--name", "s") == warm
