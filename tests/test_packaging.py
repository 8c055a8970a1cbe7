"""A non-editable install works: the wheel carries the scene (MJCF and meshes), the paper300 test set
and the shipped policies, and a copy of the package imported from another folder loads them all."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHECK = """
import regrasp_mjx, sys
from pathlib import Path
from regrasp_mjx.world.scene import load_scene
from regrasp_mjx.world.sampling import PAPER300, load_testset
from regrasp_mjx.inference.policy import load_policy, shipped_policies
assert Path(regrasp_mjx.__file__).resolve().is_relative_to(Path(sys.argv[1]).resolve()), regrasp_mjx.__file__
scene = load_scene()
episodes, _ = load_testset(PAPER300)
assert episodes.start_pos.shape == (300, 3)
assert shipped_policies() == ["decay", "default", "ensemble3", "exact", "general", "general_v1", "student_v1", "student_v2", "student_v3"]
load_policy()
print("ok", scene.model.ngeom)
"""


def test_the_wheel_alone_loads_scene_test_set_and_policies(tmp_path):
    # setuptools builds in the source tree (build/, *.egg-info): build a copy, not the checkout
    src = tmp_path / "src"
    shutil.copytree(ROOT / "regrasp_mjx", src / "regrasp_mjx", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    wheels = tmp_path / "wheels"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    (wheel,) = wheels.glob("regrasp_mjx-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for needed in (
        "regrasp_mjx/models/regrasp_scene.xml",
        "regrasp_mjx/models/meshes/needle_tube.stl",
        "regrasp_mjx/data/paper300.npz",
        "regrasp_mjx/data/general1000.npz",
        "regrasp_mjx/policies/default/policy.npz",
        "regrasp_mjx/policies/general/policy.npz",
    ):
        assert needed in names, needed
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # what pip install puts in site-packages
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "JAX_PLATFORMS": "cpu"}
    run = subprocess.run(
        [sys.executable, "-c", CHECK, str(site)], cwd=elsewhere, env=env, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip().startswith("ok")
