"""What a query asks: TaskSpec and TaskRanges (the six goal-grasp and needle keywords, checked
against what a policy was trained for), and the batch checks of poses."""

from __future__ import annotations

import numpy as np
import pytest

from regrasp_mjx.inference.policy import load_policy
from regrasp_mjx.inference.queries import TASK_FIELDS, PoseError, TaskSpec, batch_poses


@pytest.mark.parametrize("name", ["default", "general"])
def test_one_querys_scalar_path_gives_resolves_values_and_errors(name):
    """TaskRanges.vector checks scalars in plain floats; it must agree with resolve (numpy) on every
    value, in range, out of it, at its edges and wrapped (the generalist's theta* spans a turn)."""
    ranges = load_policy(name).task_ranges
    rng = np.random.default_rng(0)
    refused = 0
    for _ in range(300):
        spec = {}
        for field, (lo, hi) in ranges.as_dict().items():
            if rng.random() < 0.5:
                spread = max(hi - lo, 1e-3)
                spec[field] = float(rng.choice([lo, hi, rng.uniform(lo - 0.2 * spread, hi + 0.2 * spread)]))
        spec = TaskSpec.of(spec)
        try:
            expected, error = ranges._vector_of(spec), None
        except PoseError as e:
            expected, error = None, str(e)
        if error is None:
            np.testing.assert_allclose(ranges.vector(spec), expected, rtol=0, atol=1e-15)
        else:
            refused += 1
            with pytest.raises(PoseError) as raised:
                ranges.vector(spec)
            assert str(raised.value) == error
    assert 0 < refused < 300  # both branches exercised


def test_task_keywords_and_batches_are_checked_by_name():
    with pytest.raises(PoseError, match="needle_radius is not accepted; the goal grasp and needle: goal_alpha_rad"):
        TaskSpec.of({"needle_radius": 5.4})
    assert TaskSpec.of({}).plain and not TaskSpec.of({"goal_depth_mm": 7.0}).plain
    assert TASK_FIELDS[:2] == ("goal_alpha_rad", "goal_depth_mm")
    pose = np.r_[0.0, 0, 0, 1, 0, 0, 0]
    (a, b), single = batch_poses(needle=pose, start=pose)
    assert single and a.shape == b.shape == (1, 7)
    with pytest.raises(PoseError, match=r"poses differ in batch size: needle \(2, 7\), start \(1, 7\)"):
        batch_poses(needle=np.stack([pose, pose]), start=pose)
