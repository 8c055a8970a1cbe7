"""Test-set files: the CLI, the committed paper set, and every way a file can be wrong."""

from __future__ import annotations

import json

import numpy as np
import pytest

from regrasp_mjx import testset as testset_cli
from regrasp_mjx.world.sampling import FIELD_SHAPES, TestsetError, load_testset
from tests.conftest import PAPER_TESTSET


def test_cli_writes_a_documented_file_and_is_reproducible(tmp_path, capsys):
    out = tmp_path / "t.npz"
    assert testset_cli.main(["--n", "12", "--seed", "5", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["n"] == 12
    episodes, meta = load_testset(out)
    assert len(episodes) == 12 and meta["seed"] == 5 and meta["format"] == "regrasp_mjx.testset"
    assert set(meta["fields"]) == set(FIELD_SHAPES)
    with np.load(out, allow_pickle=False) as f:
        assert set(f.files) == {*FIELD_SHAPES, "meta"}
    again = tmp_path / "u.npz"
    testset_cli.main(["--n", "12", "--seed", "5", "--out", str(again)])
    episodes2, _ = load_testset(again)
    np.testing.assert_array_equal(episodes.start_pos, episodes2.start_pos)


def test_committed_paper_testset(paper_testset):
    episodes, meta = paper_testset
    assert len(episodes) == 300 and meta["seed"] == 2021 and meta["scene"]["jaw_angle_deg"] == 20.0
    gap = np.linalg.norm(episodes.goal_pos - episodes.start_pos, axis=1) * 1e3
    assert 3.8 < gap.mean() < 4.5  # the paper's 4.2 mm path


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.fixture()
def good_arrays():
    with np.load(PAPER_TESTSET, allow_pickle=False) as f:
        return {k: f[k][:5] if k != "meta" else f[k] for k in f.files}


def test_missing_file(tmp_path):
    with pytest.raises(TestsetError, match="test-set file not found: .*python -m regrasp_mjx.testset"):
        load_testset(tmp_path / "none.npz")


def test_not_an_npz(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(TestsetError, match="is not an .npz test-set file"):
        load_testset(bad)


def test_missing_keys(tmp_path, good_arrays):
    del good_arrays["goal_quat"]
    with pytest.raises(TestsetError, match=r"lacks keys \['goal_quat'\]"):
        load_testset(_write(tmp_path / "a.npz", **good_arrays))


def test_wrong_shape(tmp_path, good_arrays):
    good_arrays["start_pos"] = good_arrays["start_pos"][:, :2]
    with pytest.raises(TestsetError, match=r"start_pos must be a float array of shape \(5, 3\)"):
        load_testset(_write(tmp_path / "a.npz", **good_arrays))


def test_nan(tmp_path, good_arrays):
    good_arrays["needle_pos"][3, 1] = np.nan
    with pytest.raises(TestsetError, match=r"needle_pos has NaN or inf \(row 3\)"):
        load_testset(_write(tmp_path / "a.npz", **good_arrays))


def test_quaternions_near_unit_are_normalised_far_ones_refused(tmp_path, good_arrays):
    good_arrays["start_quat"][0] *= 1.0005
    episodes, _ = load_testset(_write(tmp_path / "a.npz", **good_arrays))
    np.testing.assert_allclose(np.linalg.norm(episodes.start_quat, axis=1), 1.0, atol=1e-12)
    good_arrays["start_quat"][1] *= 1.2
    with pytest.raises(TestsetError, match=r"start_quat: quaternion norm 1.2 in row 1 .* not unit"):
        load_testset(_write(tmp_path / "b.npz", **good_arrays))
