"""A recipe's jobs (:class:`Plan`): the commands ``python -m regrasp_mjx.recipe`` runs for each stage,
where their outputs go, what each needs, the memory share it takes, and on GPUs the precompile jobs
that compile the later stages' programs while the teachers train (see that command's docstring)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from regrasp_mjx.agents.ddpg_bc.config import make_config
from regrasp_mjx.core.config import TASKS
from regrasp_mjx.core.config_text import parse_overrides
from regrasp_mjx.core.jobs import Job
from regrasp_mjx.inference import robustness
from regrasp_mjx.inference.policy_file import untrained_policy
from regrasp_mjx.workflows import recipes
from regrasp_mjx.workflows.distillation import DISTILL_OUTPUTS
from regrasp_mjx.workflows.preflight import restart_args
from regrasp_mjx.workflows.recipes import Recipe


def _value(v: Any) -> str:
    return v if isinstance(v, str) else repr(v)


def _sets(pairs) -> list[str]:
    return [x for k, v in pairs for x in ("--set", f"{k}={_value(v)}")]


class Plan:
    """One recipe's jobs in ``out`` with the user's ``--set`` ``items``."""

    def __init__(self, recipe: Recipe, out: Path, items: list[str], workers: int, gpus: bool = False):
        self.recipe, self.out, self.items, self.workers, self.gpus = recipe, out, items, workers, gpus
        self.routed = recipes.check(recipe, parse_overrides(items))
        self.teacher_cfg = recipe.teacher_config(self.routed["teachers"])

    # ---- where things are ------------------------------------------------------------------
    def teacher_policy(self, seed: int) -> Path:
        folder = self.out / "teachers"
        return folder / "policy" if self.recipe.teachers.seeds == 1 else folder / f"seed{seed}" / "policy"

    def candidates(self) -> dict[str, tuple[Path, str]]:
        """name -> (policy folder, the job that makes it)."""
        seeds = range(self.recipe.teachers.seeds)
        teachers = {f"teacher_s{s}": (self.teacher_policy(s), "teachers") for s in seeds}
        if self.recipe.students is None:
            return teachers
        students = {
            f"{v}_s{s}": (self.out / "students" / v / f"s{s}" / "policy", f"students/{v}/s{s}")
            for v, _ in self.recipe.students.variants
            for s in seeds
        }
        # the students first: of equal scores the smaller network wins
        return students | teachers if self.recipe.students.with_teachers else students

    # ---- the jobs --------------------------------------------------------------------------
    def jobs(self) -> list[Job]:
        out, r, cfg = self.out, self.recipe, self.teacher_cfg
        logs = out / "logs"
        job = lambda name, stage, argv, finished, share, needs=(), **same: Job(  # noqa: E731
            name, stage, argv, finished, logs / (name.replace("/", "_") + ".txt"), share, needs, **same
        )
        demos = out / "demos"
        env_items = [(k.removeprefix("env."), v) for k, v in self.routed["teachers"].items() if k.startswith("env.")]
        task = next((n for n, t in TASKS.items() if t == make_config(r.teachers.preset).env.task), "paper")
        demos_argv = ["-m", "regrasp_mjx.demos", "--n", str(cfg.num_demos), "--seed", "0", "--task", task]
        demos_argv += ["--workers", str(self.workers), "--budget-s", str(cfg.planner_budget_s), "--out", str(demos)]
        demos_argv += ["--checker", "lean"]  # the same verdicts as MuJoCo's, so the same plans, faster
        demos_argv += [x for k, v in env_items for x in ("--env", f"{k}={_value(v)}")]
        # its planners keep every worker's core busy: a node with that many free CPUs runs it
        jobs = [job("demos", "demos", lambda: demos_argv, demos / "demos.npz", 0.3, cpus=self.workers)]

        teachers = out / "teachers"
        train_argv = ["-m", "regrasp_mjx.train", "--preset", r.teachers.preset, "--seeds", str(r.teachers.seeds)]
        train_argv += ["--demos", str(demos), "--testset", r.testset, "--out", str(teachers)]
        train_argv += _sets(r.teachers.settings) + _sets(self.routed["teachers"].items())
        jobs.append(
            job(
                "teachers",
                "teachers",
                lambda: train_argv + restart_args(teachers),
                teachers / "final_eval.json",
                r.teachers.share,
                ("demos",),
            )
        )
        if r.students is not None:
            # one program for every iteration: after the first line a variant's programs are compiled
            its = {v: r.student_config(v, self.routed["students"]).iterations for v, _ in r.students.variants}
            for variant, settings in r.students.variants:
                for s in range(r.teachers.seeds):
                    folder = out / "students" / variant / f"s{s}"
                    argv = ["-m", "regrasp_mjx.distill", "--teacher", str(self.teacher_policy(s)), "--out", str(folder)]
                    argv += ["--seed", str(s), "--testset", r.testset]
                    argv += _sets(r.students.settings) + _sets(settings) + _sets(self.routed["students"].items())
                    again = lambda folder=folder: (  # noqa: E731 - an unfinished student starts anew
                        ["--overwrite"] if any((folder / n).exists() for n in DISTILL_OUTPUTS) else []
                    )
                    jobs.append(
                        job(
                            f"students/{variant}/s{s}",
                            "students",
                            lambda argv=argv, again=again: argv + again(),
                            folder / "distill_eval.json",
                            r.students.share,
                            ("teachers",),
                            # a variant's seeds are one program set (its noise levels are constants in
                            # it; the teacher's weights and the seed are arguments)
                            programs=f"students/{variant}",
                            compiled=f"distill 1/{its[variant]}",
                        )
                    )
        sel = r.selection
        for name, (folder, maker) in self.candidates().items():
            jobs.append(
                job(
                    f"select/{name}",
                    "selection",
                    lambda folder=folder, name=name: self.select_argv(f"{name}={folder}", out / "select", name),
                    out / "select" / f"{name}.json",
                    sel.share,
                    (maker,),
                    # the candidates of one shape share programs: one compiles, the rest load it
                    programs="select/teachers" if maker == "teachers" else "select",
                )
            )
        choose = ["-m", "regrasp_mjx.recipe", r.name, "--out", str(out), "--step", "choose", *self._user_sets()]
        needs = tuple(f"select/{n}" for n in self.candidates())
        jobs.append(job("choose", "choose", lambda: choose, out / "selection.json", sel.share, needs))
        policy = f"{r.name}={out / 'policy'}"
        groups = self.report_groups()
        if len(groups) == 1:  # one job: one process compiles its programs
            modes, names = groups[0]
            argv = self.report_argv(policy, modes, names, out, "robustness")
            jobs.append(
                job(
                    "report",
                    "report",
                    lambda: argv,
                    out / "robustness.json",
                    r.report.share,
                    ("choose",),
                    **self.same(0),
                )
            )
        else:
            # on GPUs the table's rows run as parts side by side, one compiled program each (a table is
            # mostly compiling: 15 programs for the default's 38 rows), then joined
            parts = []
            for i, (mode, names) in enumerate(groups):
                argv = self.report_argv(policy, mode, names, out / "report", f"part{i:02d}")
                finished, share = out / "report" / f"part{i:02d}.json", r.report.share / len(groups)
                parts.append(
                    job(
                        f"report/part{i:02d}",
                        "report",
                        lambda argv=argv: argv,
                        finished,
                        share,
                        ("choose",),
                        **self.same(i),
                    )
                )
            merge = ["-m", "regrasp_mjx.compare", "--robustness", "--merge", *(str(p.finished) for p in parts)]
            merge += ["--out", str(out), "--name", "robustness"]
            needs = tuple(p.name for p in parts)
            jobs += [*parts, job("report", "report", lambda: merge, out / "robustness.json", 0.01, needs)]
        if self.gpus:
            jobs[2:2] = self.precompile_jobs(job, jobs)
        return jobs

    # ---- the argument lists the selection and the report share with their precompile jobs ----
    def select_argv(self, policy: str, folder: Path, name: str) -> list[str]:
        sel = self.recipe.selection
        modes = ",".join(dict.fromkeys(m for m, _ in sel.rule))
        conditions = ",".join(dict.fromkeys(c for _, c in sel.rule))
        argv = ["-m", "regrasp_mjx.compare", "--robustness", "--policy", policy]
        argv += ["--heldout", f"{sel.n}:{sel.seed}", "--no-testset", "--modes", modes, "--conditions", conditions]
        return argv + ["--out", str(folder), "--name", name]

    def report_groups(self) -> list[tuple[str, list[str] | None]]:
        """The report's jobs: one per compiled program on GPUs, else one for the whole table
        (``(modes, condition names or None for all)``)."""
        r = self.recipe.report
        modes = r.modes or tuple(robustness.MODES)
        groups = robustness.program_groups(modes, r.conditions)
        if self.gpus and len(groups) > 1:
            return groups
        return [(",".join(modes), list(r.conditions) if r.conditions else None)]

    def report_argv(self, policy: str, modes: str, names: list[str] | None, folder: Path, name: str) -> list[str]:
        r = self.recipe.report
        argv = ["-m", "regrasp_mjx.compare", "--robustness", "--policy", policy]
        if r.heldout:
            argv += ["--heldout", "{}:{}".format(*r.heldout), "--no-testset"]
        argv += ["--modes", modes]
        if names:
            argv += ["--conditions", ",".join(names)]
        return argv + ["--out", str(folder), "--name", name]

    def same(self, i: int) -> dict[str, str]:
        """The report job's programs key (with GPUs, its precompile job compiles them first)."""
        return {"programs": f"report/{i:02d}"} if self.gpus else {}

    # ---- precompile: the later stages' programs compiled while the teachers train ------------
    def untrained(self) -> dict[str, Path]:
        """Where the precompile jobs' untrained networks are: ``teacher`` (the teachers' shape and
        task) and ``candidate`` (a selection candidate's: a student's, or a teacher's without students)."""
        pre, sel = self.out / "precompile", self.recipe.selection
        out = {"teacher": pre / "teacher", "candidate": pre / ("student" if self.recipe.students else "teacher")}
        if len(sel.loop_warmups) == 1 and len(sel.loop_looks) == 1:  # the exported loop's constants are known
            out["report"] = pre / "report_candidate"
        return out

    def prepare(self) -> None:
        """Writes the untrained networks the precompile jobs run (numpy only: this process leaves
        the GPUs to its jobs). A student's is written as ``distill`` exports one: its hidden layers,
        its teacher's task."""
        if not self.gpus:
            return
        cfg, students = self.teacher_cfg, self.recipe.students
        hidden = {"teacher": cfg.hidden}
        if students is not None:
            hidden["candidate"] = self.recipe.student_config(students.variants[0][0], self.routed["students"]).hidden
        hidden.setdefault("candidate", cfg.hidden)
        hidden["report"] = hidden["candidate"]
        sel = self.recipe.selection
        loop = {"warmup_frames": sel.loop_warmups[0], "look_frames": sel.loop_looks[0]}
        for kind, folder in self.untrained().items():
            if not (folder / "policy.json").is_file():
                extra = {"closed_loop": loop} if kind == "report" else {}
                untrained_policy(folder, hidden[kind], cfg.env, note="recipe precompile", **extra)

    def precompile_jobs(self, job, jobs: list[Job]) -> list[Job]:
        """On GPUs, jobs that run each later stage's programs once on untrained networks of the
        right shapes while the teachers train (their weights are arguments, so the compiled
        programs are the ones the real jobs then load from the cache): one distillation iteration
        per student variant from an untrained teacher, one selection candidate and every report
        part on an untrained candidate. They help those jobs and fail nothing
        (:mod:`regrasp_mjx.core.jobs`); the distillations start beside the teachers once the
        demonstrations (which take every core) are made, the rest beside the students (without
        students, beside the teachers: the candidates are the teachers). The
        report's are made only where the recipe chooses among one warm-up and one look-frame count
        (constants of its programs), on an untrained candidate whose file names them."""
        r, pre, untrained = self.recipe, self.out / "precompile", self.untrained()
        names = [j.name for j in jobs]
        out: list[Job] = []
        for variant, _ in r.students.variants if r.students is not None else ():
            student = next(j for j in jobs if j.name.startswith(f"students/{variant}/"))
            folder = pre / "students" / variant
            argv = [*student.argv(), "--precompile", "--overwrite"]
            argv[argv.index("--teacher") + 1] = str(untrained["teacher"])
            argv[argv.index("--out") + 1] = str(folder)
            out.append(
                job(
                    f"precompile/students/{variant}",
                    "precompile",
                    lambda argv=argv: argv,
                    folder / "precompile.json",
                    r.students.share,
                    ("demos",),
                    programs=student.programs,
                    compiled=student.compiled,
                    helps=tuple(n for n in names if n.startswith(f"students/{variant}/")),
                )
            )
        candidate = f"untrained={untrained['candidate']}"
        # with students, after the teachers, beside the students: all eighteen at once beside the teachers
        # slowed the teacher run from 293 to 369 s on one H100 (2026-11-28; with only the two distillations
        # beside it, 293 s), and after the first distillation (which compiles its tests for minutes beside
        # the teachers) the selection's waited for memory and ended after the students (one H200)
        after = ("teachers",) if out else ("demos",)
        out.append(
            job(
                "precompile/select",
                "precompile",
                lambda: self.select_argv(candidate, pre / "select", "untrained"),
                pre / "select" / "untrained.json",
                r.selection.share,
                after,
                programs="select",
                helps=tuple(n for n in names if n.startswith("select/")),
            )
        )
        if "report" not in untrained:
            return out  # the report runs the chosen loop, whose warm-up and look frames are not known yet
        loop_candidate = f"untrained={untrained['report']}"  # a candidate's shape, the exported loop's constants
        groups = self.report_groups()
        for i, (modes, conditions) in enumerate(groups):
            real = "report" if len(groups) == 1 else f"report/part{i:02d}"
            out.append(
                job(
                    f"precompile/report/{i:02d}",
                    "precompile",
                    lambda modes=modes, conditions=conditions, i=i: self.report_argv(
                        loop_candidate, modes, conditions, pre / "report", f"part{i:02d}"
                    ),
                    pre / "report" / f"part{i:02d}.json",
                    r.report.share / len(groups),
                    after,
                    **self.same(i),
                    helps=(real,),
                )
            )
        return out

    def _user_sets(self) -> list[str]:
        return [x for item in self.items for x in ("--set", item)]
