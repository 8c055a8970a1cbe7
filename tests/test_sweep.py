"""The sweep CLI: grid expansion, per-point status and resume, a refused change of grid, and the
report's numbers from hand-written logs."""

from __future__ import annotations

import json

import pytest

from regrasp_mjx import sweep
from regrasp_mjx.core import cluster
from regrasp_mjx.core.config import ConfigError


def test_grid_points_are_the_product_in_order():
    grid = sweep.parse_grid(["bc_decay_epochs=0|100", "critic_layer_norm=False|True", "hidden=(64,64)|(32,)"])
    assert grid[2] == ("hidden", [(64, 64), (32,)])  # literals, commas inside tuples kept
    pts = sweep.points(grid)
    assert len(pts) == 8
    assert pts[0] == {"bc_decay_epochs": 0, "critic_layer_norm": False, "hidden": (64, 64)}
    assert pts[1]["hidden"] == (32,) and pts[-1] == {"bc_decay_epochs": 100, "critic_layer_norm": True, "hidden": (32,)}
    assert sweep.points([]) == [{}]  # no grid: one run
    assert sweep.point_name(3, pts[1]) == "03_bc_decay_epochs=0_critic_layer_norm=False_hidden=32"
    with pytest.raises(ConfigError, match="KEY=V1"):
        sweep.parse_grid(["bc_decay_epochs"])
    with pytest.raises(ConfigError, match="given twice"):
        sweep.parse_grid(["a=1|2", "a=3"])
    with pytest.raises(ConfigError, match="listed twice"):
        sweep.parse_grid(["a=1|1"])


def _log(path, successes):
    """A log.jsonl of one setting: per seed, the test success of each epoch."""
    rows = []
    for seed, series in enumerate(successes):
        for epoch, s in enumerate(series, 1):
            rows.append(
                {
                    "epoch": epoch,
                    "seed": seed,
                    "setting": None,
                    "test": {"success_rate": s, "collision_rate": 1 - s, "path_length_mm": 4.0},
                    "validation": {"success_rate": s},
                    "wall_s": 10.0 * epoch,
                }
            )
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")


def test_status_resume_report_and_a_changed_grid_refused(tmp_path, capsys):
    argv = ["--out", str(tmp_path), "--preset", "smoke", "--seeds", "2", "--grid", "lr_actor=0.001|0.002"]
    names = ["00_lr_actor=0.001", "01_lr_actor=0.002"]
    # point 0 finished (a log and its final evaluation), point 1 left a checkpoint when killed
    (tmp_path / names[0]).mkdir(parents=True)
    _log(tmp_path / names[0] / "log.jsonl", [[0.5, 0.8, 0.9], [0.6, 0.9, 0.7]])
    (tmp_path / names[0] / "final_eval.json").write_text(
        json.dumps(
            {
                "seeds": [
                    {
                        "setting": None,
                        "test": {"bare": {"success_rate": s}, "shielded": {"success_rate": 1.0}},
                        "best_epoch": e,
                    }
                    for s, e in ((0.9, 3), (0.9, 2))
                ]
            }
        )
    )
    (tmp_path / names[1] / "checkpoint").mkdir(parents=True)
    (tmp_path / names[1] / "checkpoint" / "meta.json").write_text("{}")
    assert sweep.main([*argv, "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("[done]") and "--resume" not in out[0]
    assert out[1].startswith("[resume]") and out[1].endswith("--set lr_actor=0.002 --resume")

    assert sweep.main([*argv, "--report"]) == 0
    md = (tmp_path / "sweep.md").read_text()
    # point 0: last epoch 0.9 / 0.7 -> 0.800 ± 0.100; mean of its 3 epochs 2.2 / 3 for both seeds; best
    # 0.9 / 0.9; exported 0.9 / 0.9, shielded 1.0; collision at the last epoch 0.1 / 0.3; path 4 mm
    assert (
        "| 00_lr_actor=0.001 | lr_actor=0.001 | - | 3 | 0.800 ± 0.100 | 0.733 ± 0.000 | 0.900 ± 0.000 | 0.900 ± 0.000 | 1.000 ± 0.000 | 0.200 ± 0.100 | 4.000 ± 0.000 |"
        in md
    )
    assert "| 01_lr_actor=0.002 | lr_actor=0.002 | - | - | not run yet |" in md
    assert (tmp_path / "sweep.png").is_file()
    saved = json.loads((tmp_path / "sweep.json").read_text())
    assert saved["points"] == {names[0]: {"lr_actor": 0.001}, names[1]: {"lr_actor": 0.002}}

    # the same folder with another grid is refused, before anything runs
    assert sweep.main(["--out", str(tmp_path), "--preset", "smoke", "--seeds", "2", "--grid", "lr_actor=0.003"]) == 2
    assert "holds a sweep with other arguments" in capsys.readouterr().err
    # a bad value in any point is refused up front, naming the field
    assert sweep.main(["--out", str(tmp_path / "new"), "--preset", "smoke", "--grid", "gamma=0.9|1.5"]) == 2
    assert "gamma=1.5 is not accepted" in capsys.readouterr().err


def test_local_gpus_follow_the_request_and_visible_devices_and_a_cluster_refuses_gpus(monkeypatch):
    assert cluster.local_gpus("0, 2") == ["0", "2"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1,3")
    assert cluster.local_gpus(None) == ["1", "3"]
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    monkeypatch.setattr(cluster.shutil, "which", lambda _: None)
    assert cluster.local_gpus(None) == []  # no GPU: Ray started here has none, a job takes the CPUs
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert cluster.check_options(None, "0") is None  # Ray started here, on GPU 0
    monkeypatch.setenv("RAY_ADDRESS", "head:6379")
    assert cluster.check_options(None, None) == "head:6379"  # RAY_ADDRESS names the cluster
    with pytest.raises(ConfigError, match=r"--gpus 0 is not accepted with a cluster \(head:6379\)"):
        cluster.check_options(None, "0")


def test_a_second_sweep_into_a_folder_in_use_is_refused_before_ray_starts(tmp_path, capsys, monkeypatch):
    from regrasp_mjx.core.host_loop import folder_lock

    started = []
    monkeypatch.setattr(sweep, "connect", lambda *a, **k: started.append(a))  # Ray must not be reached
    with folder_lock(tmp_path / "s"):  # another sweep (or recipe) writes into it now
        assert sweep.main(["--out", str(tmp_path / "s"), "--preset", "smoke", "--seeds", "1"]) == 2
    assert "is in use by another run (pid " in capsys.readouterr().err and not started
