"""The analysis helpers the notebooks use: logs, the funnel of Fig. 5, Table II, figure output and
experiment results (the renderer's tests: ``tests/test_render.py``)."""

from __future__ import annotations

import json
import math

import jax
import numpy as np
import pytest

from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.workflows import analysis
from regrasp_mjx.world.sampling import episode_poses
from tests.conftest import ROOT

RESULTS = ROOT / "experiments" / "results"


def _pose(ep, field, i):
    return episode_poses(ep)[("needle", "start", "goal").index(field)][i]


# ---- logs --------------------------------------------------------------------------------------
def test_write_results_writes_the_table_and_the_rows_whole_and_nothing_without_a_folder(tmp_path):
    from regrasp_mjx.core.atomic import write_results

    write_results(tmp_path / "r", "t", ["| a |", "| 1 |"], {"rows": [1.5]})
    assert (tmp_path / "r" / "t.md").read_text() == "| a |\n| 1 |\n"
    assert json.loads((tmp_path / "r" / "t.json").read_text()) == {"rows": [1.5]}
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["t.json", "t.md"]  # no temporary left
    write_results(None, "t", ["x"], {})  # experiments run without --out write nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_figures_and_csv_tables_are_written_whole(tmp_path):
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from regrasp_mjx.core.atomic import write_csv, write_figure

    write_csv(tmp_path / "t.csv", ["name", "rate"], [["a, b", 0.5], ["c", 1]])
    assert list(csv.reader((tmp_path / "t.csv").open(newline=""))) == [["name", "rate"], ["a, b", "0.5"], ["c", "1"]]
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    write_figure(tmp_path / "f.png", fig, dpi=50)
    plt.close(fig)
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    class Broken:  # a figure that fails half-way leaves the earlier file as it was
        def savefig(self, f, **kw):
            f.write(b"half")
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_figure(tmp_path / "f.png", Broken())
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png", "t.csv"]  # no temporary left


def test_read_log_groups_seeds_sorts_epochs_and_flattens(tmp_path):
    rows = [
        {"epoch": 2, "seed": 1, "test": {"success_rate": 0.5}, "wall_s": 20.0},
        {"epoch": 1, "seed": 1, "test": {"success_rate": 0.25}, "wall_s": 10.0},
        {"epoch": 1, "seed": 0, "test": {"success_rate": 0.1}, "wall_s": 9.0, "extra": None},
        {"epoch": 2, "seed": 0, "test": {"success_rate": 0.2}, "wall_s": 19.0, "extra": 3},
    ]
    path = tmp_path / "log.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    log = analysis.read_log(path)
    assert list(log) == [0, 1]
    np.testing.assert_array_equal(log[1]["epoch"], [1, 2])
    np.testing.assert_array_equal(log[1]["test.success_rate"], [0.25, 0.5])
    np.testing.assert_array_equal(log[0]["extra"], [np.nan, 3.0])  # None -> NaN
    epochs, band = analysis.seed_band(log, "wall_s")
    np.testing.assert_array_equal(epochs, [1, 2])
    np.testing.assert_array_equal(band, [[9.0, 19.0], [10.0, 20.0]])
    with pytest.raises(analysis.ResultsError, match="'extra' is not in the log of seeds \\[1\\]"):
        analysis.seed_band(log, "extra")


def test_read_log_bad_files_are_clear_errors(tmp_path):
    with pytest.raises(analysis.ResultsError, match="training log not found"):
        analysis.read_log(tmp_path / "missing.jsonl")
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"epoch": 1}\n{"epoch": 2\n')
    with pytest.raises(analysis.ResultsError, match="bad.jsonl:2 is not JSON"):
        analysis.read_log(bad)
    bad.write_text('{"epoch": 1}\n[1, 2]\n')
    with pytest.raises(analysis.ResultsError, match=":2 is not a log row"):
        analysis.read_log(bad)
    bad.write_text("\n")
    with pytest.raises(analysis.ResultsError, match="has no rows"):
        analysis.read_log(bad)


def test_shipped_table1_logs_read():
    path = RESULTS / "table1_paper" / "log.jsonl"  # three settings x 3 seeds in one log
    assert analysis.settings_in_log(path) == ["ddpg_bc", "targeted", "mixed"]
    log = analysis.read_log(path, "mixed")
    epochs, success = analysis.seed_band(log, "test.success_rate")
    assert sorted(log) == [0, 1, 2] and success.shape == (3, 200) and epochs[0] == 1 and epochs[-1] == 200
    assert success[:, 0].max() < 0.5 < success[:, -1].min()  # learned
    with pytest.raises(analysis.ResultsError, match="no rows of setting 'nope'"):
        analysis.read_log(path, "nope")
    # a log of one setting has none named
    assert analysis.settings_in_log(RESULTS / "ablation" / "ours" / "log.jsonl") == []


def test_in_needle_frame_by_hand():
    half = math.sqrt(0.5)
    needle = np.array([1.0, 2.0, 3.0, half, 0.0, 0.0, half])  # 90 deg about z
    points = np.array([[1.0, 2.001, 3.0], [1.0, 2.0, 3.002]])
    # A point 1 mm along e_g's y lies along the needle's x; z stays z.
    np.testing.assert_allclose(
        analysis.in_needle_frame_mm(needle, points), [[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], atol=2e-4
    )
    both = analysis.in_needle_frame_mm(np.stack([needle, needle]), points)
    np.testing.assert_allclose(both, analysis.in_needle_frame_mm(needle, points))


# ---- Fig. 5 ------------------------------------------------------------------------------------
def test_free_fraction_funnel_shape(env, paper_testset):
    episodes, _ = paper_testset
    sub = jax.tree.map(lambda x: x[:60], episodes)
    free = analysis.free_fraction(env, sub, [0.0, 1.5, 300.0], samples=32, seed=1)
    # At the goal every pose is free (goals are drawn collision-free); 300 mm away the 54 mm tool
    # cannot reach anything; 1.5 mm off most directions push a jaw into the wire.
    assert free[0] == 1.0 and free[2] == 1.0
    assert free[1] < 0.6
    same = analysis.free_fraction(env, sub, [0.0, 1.5, 300.0], samples=32, seed=1)
    np.testing.assert_array_equal(free, same)  # a seed gives the same numbers


def test_free_fraction_agrees_with_the_host_checker(env, paper_testset):
    """The same estimate made independently: numpy-drawn offsets checked by CPU MuJoCo."""
    episodes, _ = paper_testset
    n, samples, d = 40, 50, 1.5
    sub = jax.tree.map(lambda x: x[:n], episodes)
    batched = analysis.free_fraction(env, sub, [d], samples=samples, seed=3)[0]
    checker = HostChecker(env.scene)
    rng = np.random.default_rng(0)
    free = 0
    for i in range(n):
        needle, goal = _pose(episodes, "needle", i), _pose(episodes, "goal", i)
        for _ in range(samples):
            u = rng.normal(size=3)
            pos = goal[:3] + d * 1e-3 * u / np.linalg.norm(u)
            free += not checker.collides(needle[:3], needle[3:], pos, goal[3:])
    host = free / (n * samples)
    sigma = math.sqrt(host * (1 - host) / (n * samples))
    assert abs(batched - host) < 4 * sigma * math.sqrt(2) + 0.02, (batched, host)


def test_free_fraction_bad_arguments(env, paper_testset):
    episodes, _ = paper_testset
    for kwargs, match in [
        ({"distances_mm": []}, "non-empty"),
        ({"distances_mm": [1.0, -1.0]}, ">= 0"),
        ({"distances_mm": [np.nan]}, "finite"),
        ({"distances_mm": [1.0], "samples": 0}, "samples"),
        ({"distances_mm": [1.0], "rot_deg": 270.0}, "rot_deg"),
    ]:
        with pytest.raises(ValueError, match=match):
            analysis.free_fraction(env, episodes, **kwargs)


# ---- Table II ----------------------------------------------------------------------------------
def test_table2_from_shipped_results():
    rows = analysis.table2(RESULTS)
    by = {r["method"]: r for r in rows}
    assert by["BIT* (R)"]["success"] == 1.0 and by["BIT* (R)"]["kind"] == "planner"
    assert abs(by["BIT* (R)"]["median_ms"] - 26.08) < 0.01
    shipped = by["policy, shipped (distilled 2x256 network + shield)"]
    assert shipped["success"] == 1.0 and shipped["kind"] == "policy" and abs(shipped["path_mm"] - 4.21) < 0.01
    assert shipped["median_ms"] < 1.0  # one core of the H100 host (issue 14's target)
    assert by["policy, 3-network ensemble + shield (earlier default)"]["success"] == 1.0
    assert by["paper: BIT* (R)"]["mean_ms"] == 2590.5 and by["paper: BFMT* (R)"]["mean_ms"] is None
    # Another jaw angle: only that angle's planner rows.
    planners_35 = [r["method"] for r in analysis.table2(RESULTS, jaw_angle_deg=35.0) if r["kind"] == "planner"]
    assert planners_35 == ["straight line", "BIT* (R)"]


def test_table2_and_markdown_errors_and_format(tmp_path):
    with pytest.raises(analysis.ResultsError, match="planners.csv"):
        analysis.table2(tmp_path)
    (tmp_path / "planners.csv").write_text((RESULTS / "planners.csv").read_text())
    with pytest.raises(analysis.ResultsError, match="no rows for a jaw angle of 50.0"):
        analysis.table2(tmp_path, jaw_angle_deg=50.0)
    with pytest.raises(analysis.ResultsError, match="eval_cpu1_single.json"):
        analysis.table2(tmp_path)
    text = analysis.markdown_table(
        [{"a": "x", "b": 0.12345}, {"a": "y", "b": None}], [("a", "name", ""), ("b", "value", ".2f")]
    )
    assert text == "| name | value |\n| --- | --- |\n| x | 0.12 |\n| y | - |"


# ---- figures -----------------------------------------------------------------------------------
def test_save_figure_only_when_asked(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2, 2))
    monkeypatch.delenv(analysis.FIGURES_ENV, raising=False)
    assert analysis.save_figure(fig, "x.png") is None
    monkeypatch.setenv(analysis.FIGURES_ENV, str(tmp_path / "figs"))
    path = analysis.save_figure(fig, "x.png")
    assert path == tmp_path / "figs" / "x.png" and path.read_bytes()[:4] == b"\x89PNG"
    frames = np.zeros((3, 8, 10, 3), np.uint8)
    gif = analysis.save_figure(frames, "v.gif")
    assert gif.read_bytes()[:3] == b"GIF"
    plt.close(fig)
    with pytest.raises(analysis.ResultsError, match="no experiments/results"):
        analysis.repo_root(tmp_path)
    assert analysis.repo_root(ROOT / "notebooks") == ROOT


# ---- rendering ---------------------------------------------------------------------------------
