"""Our demonstrations as a Minari dataset (issue 71): a demonstration set of each task exported by
``python -m regrasp_mjx.export_minari``, read back by ``minari.load_dataset``, its episodes replayed
in the recovered environment from their stored resets to the same observations and the same
success; the command's refusals; the package without Minari."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import runpy
import subprocess
import sys
from pathlib import Path

import gymnasium
import jax
import numpy as np
import pytest

from regrasp_mjx import export_minari
from regrasp_mjx.core.config import TASKS, EnvConfig, SceneConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.interfaces import minari_export
from regrasp_mjx.planning.demonstrations import problem_sampler
from regrasp_mjx.planning.episodes import load_demos, make_replay, replay_paths, save_demos
from tests.conftest import ROOT

needs_minari = pytest.mark.skipif(
    bool(minari_export.missing_packages()),
    reason=f"the minari extra is not installed ({', '.join(minari_export.missing_packages())} missing): "
    f"{minari_export.INSTALL}",
)
SNIPPET = next(
    s for s in re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "learners.md").read_text(), re.S) if "minari" in s
)
DOCUMENTED_ID = re.search(r'load_dataset\("([^"]+)"\)', SNIPPET).group(1)
IDS = {"paper": DOCUMENTED_ID, "general": "regrasp_mjx/general-tiny-v0"}
SEED = 3


def tiny_demos(folder: Path, task: str, n: int = 6) -> Path:
    """A demonstration set as ``python -m regrasp_mjx.demos`` writes one (problem i drawn from the
    seed, the path replayed, the settings in its meta), planned in no time: with 60-degree jaws the
    straight line from start to goal reaches most goals (tests/test_learner.py's easy problem)."""
    config = EnvConfig(scene=SceneConfig(jaw_angle_deg=60.0), task=TASKS[task], horizon=40)
    env = RegraspEnv(dataclasses.replace(config, check_actions=False))
    problems = problem_sampler(env, SEED)(np.arange(2 * n))
    paths = [
        np.stack(
            [np.r_[problems.start_pos[i], problems.start_quat[i]], np.r_[problems.goal_pos[i], problems.goal_quat[i]]]
        )
        for i in range(2 * n)
    ]
    ok, rows = replay_paths(env, make_replay(env), problems, paths, batch=2 * n)
    episodes = [{**r, "problem_index": i, "plan_time_s": 0.0} for i, r in enumerate(rows) if ok[i]][:n]
    assert len(episodes) == n
    settings = {
        "seed": SEED,
        "planner": {"planner": "straight line", "direction": "forward"},
        "env": dataclasses.asdict(config),
    }
    return save_demos(folder / "demos.npz", episodes, {"settings": settings, "n": n})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Each task's tiny set exported once, by the command, into one Minari root: ``(root, {task: (demos, summary)})``."""
    if minari_export.missing_packages():
        pytest.skip(f"the minari extra is not installed: {minari_export.INSTALL}")
    root = tmp_path_factory.mktemp("minari")
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(root))
        for task, name in IDS.items():
            demos = tiny_demos(tmp_path_factory.mktemp(task), task)
            printed = io.StringIO()
            with contextlib.redirect_stdout(printed):
                assert export_minari.main(["--demos", str(demos.parent), "--name", name, "--quiet"]) == 0
            out[task] = (demos, json.loads(printed.getvalue().strip().splitlines()[-1]))
    return root, out


@needs_minari
@pytest.mark.parametrize("task", ["paper", "general"])
def test_an_exported_set_loads_and_its_episodes_replay_to_their_success(exported, task, monkeypatch):
    import minari

    root, made = exported
    demos_path, summary = made[task]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    demos = load_demos(demos_path)
    assert summary["episodes"] == demos.num_episodes and summary["left_out"] == []
    assert summary["steps"] == int(demos.length.sum()) and summary["max_obs_difference"] < 1e-5
    dataset = minari.load_dataset(IDS[task])
    name = {"paper": "NeedleRegrasp", "general": "NeedleRegraspGeneral"}[task]
    assert dataset.env_spec.id == f"regrasp_mjx/{name}-v0" and len(dataset) == demos.num_episodes
    env = dataset.recover_environment()
    made_env = gymnasium.make(
        f"regrasp_mjx/{name}-v0", config_overrides={"env.scene.jaw_angle_deg": 60.0, "env.horizon": 40}
    )
    for space in ("observation_space", "action_space"):
        assert getattr(dataset, space) == getattr(env, space) == getattr(made_env, space)
    assert env.unwrapped.registry_env.env_config == made_env.unwrapped.registry_env.env_config
    starts = np.concatenate([[0], np.cumsum(demos.length)])
    for i, episode in enumerate(dataset.iterate_episodes()):
        obs, info = env.reset(**minari_export.reset_arguments(dataset, i))
        for k in obs:
            np.testing.assert_array_equal(obs[k], episode.observations[k][0])
        for t, action in enumerate(episode.actions):
            obs, reward, terminated, truncated, info = env.step(action)
            for k in obs:
                np.testing.assert_array_equal(obs[k], episode.observations[k][t + 1])
            assert (reward, terminated, truncated) == (
                episode.rewards[t],
                episode.terminations[t],
                episode.truncations[t],
            )
        assert info["is_success"] and episode.infos["is_success"][-1] and episode.terminations[-1]
        assert not episode.truncations.any()
        # the recorded episode is the demonstration: its actions, rewards and observations
        lo, hi = starts[i], starts[i + 1]
        np.testing.assert_array_equal(episode.actions, demos.action[lo:hi])
        np.testing.assert_allclose(episode.rewards, demos.reward[lo:hi], atol=1e-7)
        np.testing.assert_allclose(episode.observations["observation"][:-1], demos.obs[lo:hi], atol=1e-5)
    about = dataset.storage.metadata["regrasp_mjx"]
    assert about["demonstrations"] == str(demos_path.resolve()) and about["seed"] == SEED
    assert (
        about["planner"]["planner"] == "straight line" and about["version"] == minari_export.versions()["regrasp_mjx"]
    )
    assert about["config_overrides"] == {"env.scene.jaw_angle_deg": 60.0, "env.horizon": 40}


@needs_minari
def test_the_learners_page_dataset_snippet_runs(exported, monkeypatch, capsys):
    """docs/learners.md's Minari snippet, as written, on the paper set exported under its id."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(exported[0]))
    exec(compile(SNIPPET, "docs/learners.md", "exec"), {"__name__": "__docs__"})
    out = capsys.readouterr().out.strip()
    assert out.startswith("6 True") and out.endswith("True"), out


def _tree(folder: Path) -> dict[str, int]:
    """Every path below ``folder``, with its files' times (a folder's own changes with the command's write probe)."""
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns if p.is_file() else 0 for p in sorted(folder.rglob("*"))}


@needs_minari
@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--name", "regrasp_mjx/paper"], "is not accepted: a Minari dataset id [NAMESPACE/]NAME-vVERSION"),
        (["--name", "a b-v0"], "is not accepted: a Minari dataset id"),
        (["--name", DOCUMENTED_ID], "a dataset of that id exists"),
        (["--demos", "{w}/nothing", "--name", "x-v0"], "demonstration set not found"),
        (["--demos", "{w}/old", "--name", "x-v0"], "names no seed and environment"),
        (
            ["--name", "x-v0", "--root", "/proc/regrasp_mjx_x"],
            "/proc is not a writable folder; accepted: MINARI_DATASETS_PATH",
        ),
    ],
)
def test_export_refuses_bad_input_and_changes_nothing(exported, argv, fragment, tmp_path, monkeypatch, capsys):
    root = exported[0]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    d = load_demos(exported[1]["paper"][0])  # its first step, as a set from before its settings were recorded
    one = {k: getattr(d, k)[:1] for k in ("obs", "action", "reward", "done", "next_obs")}
    save_demos(
        tmp_path / "old" / "demos.npz", [{**one, "path_length_mm": 1.0, "problem_index": 0, "plan_time_s": 0.0}], {}
    )
    if "--root" in argv:  # MINARI_DATASETS_PATH, which the command reads
        monkeypatch.setenv("MINARI_DATASETS_PATH", argv[-1])
        argv = argv[:-2]
    if "--demos" not in argv:
        argv = ["--demos", str(exported[1]["paper"][0]), *argv]
    before = _tree(root)
    with pytest.raises(SystemExit) as exit_:
        raise SystemExit(export_minari.main([a.format(w=tmp_path) for a in argv]))
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err, err
    assert _tree(root) == before


@needs_minari
@pytest.mark.filterwarnings("ignore:.*found in sys.modules:RuntimeWarning")  # runpy: run as python -m does
def test_ctrl_c_leaves_nothing_and_overwrite_replaces(exported, monkeypatch, capsys):
    """Interrupted as ``python -m`` runs it (one line, exit 130) after some episodes: no dataset, no
    staging folder; then written, and written again over itself with --overwrite."""
    import minari

    root, made = exported
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    argv = ["--demos", str(made["paper"][0].parent), "--name", "regrasp_mjx/cut-v0", "--quiet"]
    before = _tree(root)
    record, calls = minari_export.record, []

    def interrupted(*args):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return record(*args)

    monkeypatch.setattr(minari_export, "CHUNK", 2)  # two chunks written before the interrupt
    monkeypatch.setattr(minari_export, "record", interrupted)
    monkeypatch.setattr(sys, "argv", ["export_minari", *argv])
    cache = jax.config.jax_compilation_cache_dir
    try:
        with pytest.raises(SystemExit) as exit_:
            runpy.run_module("regrasp_mjx.export_minari", run_name="__main__")
    finally:
        jax.config.update("jax_compilation_cache_dir", cache)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 130 and err == ["interrupted; nothing was written: run the same command again"], err
    assert _tree(root) == before  # neither the dataset nor the staging folder
    monkeypatch.setattr(minari_export, "record", record)
    assert export_minari.main(argv) == 0
    first = minari.load_dataset("regrasp_mjx/cut-v0").storage.metadata["regrasp_mjx"]["demonstrations_sha256"]
    monkeypatch.setattr(minari_export, "CHUNK", 256)  # one chunk this time: the same dataset
    assert export_minari.main([*argv, "--overwrite"]) == 0
    again = minari.load_dataset("regrasp_mjx/cut-v0")
    assert len(again) == 6 and again.storage.metadata["regrasp_mjx"]["demonstrations_sha256"] == first
    assert not [p for p in root.iterdir() if p.name.startswith(minari_export.STAGING)]
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["episodes"] == 6


def test_the_package_and_the_command_without_minari(tmp_path):
    """``import regrasp_mjx`` never imports Minari, and the command without it says how to install it."""
    code = (
        "import sys\n"
        "import regrasp_mjx\n"
        "assert 'minari' not in sys.modules and 'h5py' not in sys.modules\n"
        "sys.modules['minari'] = None\n"  # an import of minari now fails as it does where it is not installed
        "from regrasp_mjx import export_minari\n"
        f"sys.exit(export_minari.main(['--demos', {str(tmp_path)!r}, '--name', 'x-v0']))\n"
    )
    env = {**os.environ, "MINARI_DATASETS_PATH": str(tmp_path / "minari")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    assert r.returncode == 2, r.stderr
    assert 'minari not installed, which a Minari export needs; accepted: pip install -e ".[minari]"' in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "minari").exists()
