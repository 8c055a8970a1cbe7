"""What a training run checks before the work (:func:`before_the_work`: its test set, demonstrations
and batch) and what an earlier run left in its folder (:func:`run_outputs`; :func:`restart_args`,
what starting it again needs): for ``python -m regrasp_mjx.train``, a sweep and a recipe."""

from __future__ import annotations

from pathlib import Path

from regrasp_mjx.inference.queries import PoseError, TaskRanges, TaskSpec
from regrasp_mjx.planning.episodes import DemosError, load_demos
from regrasp_mjx.workflows.trainer import check_demos
from regrasp_mjx.world.sampling import TestsetError, episode_needles, load_testset

# what a training run writes into OUT (besides files of others, e.g. a sweep's stdout)
RUN_OUTPUTS = ("log.jsonl", "checkpoint", "policy", "policy_last", "final_eval.json", "demos", "student")


def run_outputs(out: Path) -> list[Path]:
    """An earlier run's outputs in ``out``: its files and folders, its seeds' and settings' folders
    (those holding ``seed*``) and its TensorBoard files."""
    if not out.is_dir():
        return []
    found = []
    for entry in sorted(out.iterdir()):
        name = entry.name
        if (
            name in RUN_OUTPUTS
            or name.startswith(("seed", "events.out.tfevents"))
            or (entry.is_dir() and any(entry.glob("seed*")))
        ):
            found.append(entry)
    return found


def restart_args(out: Path) -> list[str]:
    """What starting this folder's run again needs: ``--resume`` where a checkpoint is, ``--overwrite``
    where an earlier run left outputs without one (it never got that far), else nothing."""
    if (out / "checkpoint" / "meta.json").is_file():
        return ["--resume"]
    return ["--overwrite"] if run_outputs(out) else []


def before_the_work(cfg, testset: str, demos: str | None = None) -> str | None:
    """What would only fail after minutes of demonstrations and training, or after the run's folder
    is made: a test set of another task than the run's, ``demos`` (a folder) missing or made for
    another task, or fewer demonstration transitions than one batch could ever hold."""
    try:
        episodes, _ = load_testset(testset)
        TaskRanges.of(cfg.env).values(len(episodes.needle_pos), TaskSpec.of(episode_needles(episodes)))
        if demos is not None:
            check_demos(load_demos(demos), cfg.env, Path(demos))
    except TestsetError as err:
        return f"--testset {testset}: {err}"
    except DemosError as err:
        return f"--demos {demos}: {err}"
    except PoseError as err:
        return (
            f"--testset {testset} holds problems of another task than this run trains ({err}); accepted: "
            "paper300 for the paper task, general1000 for --task general"
        )
    most = cfg.num_demos * cfg.env.horizon  # every demonstration as long as an episode can be
    if cfg.demo_batch > most:
        return (
            f"batch_size={cfg.batch_size} needs {cfg.demo_batch} demonstration transitions a batch, more than "
            f"{cfg.num_demos} demonstrations can hold ({most}); accepted: a smaller batch_size or demo_fraction, "
            "or more num_demos"
        )
    return None
