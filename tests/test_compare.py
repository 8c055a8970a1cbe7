"""``python -m regrasp_mjx.compare``: several policies as ``Policy.plan`` plans them, the generalist's
breakdown worked by hand, robustness tables written per policy and merged from parts."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from regrasp_mjx import compare
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.inference import robustness, robustness_report
from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.testset_plans import plan_testset
from regrasp_mjx.world.testsets import make_testset


@pytest.mark.slow
def test_compare_plans_each_policy_bare_and_shielded_as_policy_plan_does(tmp_path):
    argv = ["--policy", "default", "--policy", "again=", "--no-testset", "--heldout", "6:5", "--out", str(tmp_path)]
    assert compare.main(argv) == 0
    data = json.loads((tmp_path / "compare.json").read_text())
    assert [(r["policy"], r["rollout"]) for r in data["rows"]] == [
        ("default", "bare"), ("default", "shielded"), ("again", "bare"), ("again", "shielded"),
    ]  # fmt: skip
    policy = load_policy("default")
    episodes = make_testset(6, 5, policy.env_config)
    for r in data["rows"]:
        plan = plan_testset(policy, episodes, r["rollout"] == "shielded")
        assert r["testset"] == "held-out 6 (seed 5)" and r["problems"] == 6
        assert r["success_rate"] == pytest.approx(float(np.mean(plan.success)))
    shape = "x".join(map(str, policy.hidden))
    assert f"| again | {shape} | held-out 6 (seed 5) | shielded |" in (tmp_path / "compare.md").read_text()
    assert "breakdown" not in data  # no general policy on general1000


def test_breakdown_by_needle_radius_and_goal_angle_by_hand():
    alpha0 = 10 * math.pi / 9
    episodes = SimpleNamespace(
        needle_radius=np.array([4.5, 5.0, 7.0, 11.9]) * 1e-3,
        goal_grasp=np.array([[alpha0 + 0.01, 0, 0, 0]] * 3 + [[13 * math.pi / 9, 0, 0, 0]]),
    )
    per_problem = {"a": np.array([1, 0, 1, 1], bool), "b": np.array([1, 1, 0, 1], bool)}
    data, lines = compare.breakdown(episodes, per_problem)
    edges, rates, counts = data["breakdown"]["by_radius_mm"]
    assert counts == [2, 1, 0, 1] and rates[:2] == [0.75, 0.5] and math.isnan(rates[2]) and rates[3] == 1.0
    _, rates, counts = data["breakdown"]["by_alpha_rad"]
    assert counts == [3, 0, 0, 1] and rates[0] == pytest.approx(4 / 6) and rates[3] == 1.0  # the top edge: last bin
    assert data["per_problem"]["bare_success"] == {"a": [1, 0, 1, 1], "b": [1, 1, 0, 1]}
    assert "| success | 0.750 | 0.500 | nan | 1.000 |" in lines


def _table(policy, rows, machine="m1", digest="h1", problems="paper300"):
    return {"policy": policy, "folder": policy, "policy_hash": digest, "hidden": [256, 256], "problems": problems,
            "machine": machine, "seed": 0, "wall_s": 1.0, "rows": [{"condition": c, "mode": "open"} for c in rows]}  # fmt: skip


def test_merge_joins_the_parts_of_a_policy_in_condition_order():
    noise, margin = robustness.CONDITIONS[1].name, robustness.CONDITIONS[-1].name
    parts = [
        {"tables": [_table("default", [margin]), _table("exact", ["exact"])]},
        {"tables": [_table("default", [noise, "exact"], machine="m2")]},
    ]
    merged = robustness_report.merge(parts)
    assert [t["policy"] for t in merged] == ["default", "exact"]
    assert [r["condition"] for r in merged[0]["rows"]] == ["exact", noise, margin]
    assert merged[0]["machine"] == "m1; m2" and merged[0]["wall_s"] == 2.0
    assert parts[0]["tables"][0]["rows"] == [{"condition": margin, "mode": "open"}]  # the parts are not changed
    with pytest.raises(ConfigError, match="default was measured with another policy file or problems"):
        robustness_report.merge(
            [{"tables": [_table("default", ["exact"])]}, {"tables": [_table("default", ["x"], digest="h2")]}]
        )


def test_compare_writes_a_robustness_table_naming_the_policys_hash(tmp_path, capsys):
    argv = ["--robustness", "--policy", "default", "--no-testset", "--heldout", "5:3", "--conditions", "exact"]
    assert compare.main([*argv, "--modes", "open", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "robustness.json").read_text())
    (table,) = data["tables"]
    assert table["policy_hash"] == robustness.policy_hash("default") and table["problems"] == "held-out 5 (seed 3)"
    assert [(r["condition"], r["mode"], r["problems"]) for r in table["rows"]] == [("exact", "open", 5)]
    assert (
        compare.main(["--robustness", "--merge", str(tmp_path / "robustness.json"), "--out", str(tmp_path / "m")]) == 0
    )
    merged = json.loads((tmp_path / "m" / "robustness.json").read_text())["tables"]
    assert merged[0]["rows"] == table["rows"]
    assert f"hash {table['policy_hash']}" in (tmp_path / "m" / "robustness.md").read_text()
