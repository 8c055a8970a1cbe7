"""The jaws opening on the way (issue 67): every collision path of the environment takes each row's own
opening (the distances, the XLA walk, the Pallas kernel), the opening sweep inside a step is proved
clear or counted a collision, and the environment's own rule opens once there is room. The lean CPU
path's jaws: tests/test_lean_jaw.py."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from regrasp_mjx.core.config import ConfigError, EnvConfig, SceneConfig
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.world import continuous_walk, jaw, walk_kernel
from regrasp_mjx.world.scene import load_scene

BATCH = 256


@pytest.fixture(scope="module")
def envs():
    """The 20 degree scene's environment, the one built at 60 degrees, and one that opens to 60."""
    return (
        RegraspEnv(EnvConfig()),
        RegraspEnv(EnvConfig(scene=SceneConfig(jaw_angle_deg=60.0))),
        RegraspEnv(EnvConfig(jaw_open_deg=60.0)),
    )


@pytest.fixture(scope="module")
def problems(envs):
    """A batch of the paper's starts (drawn for 20 degrees) and one random action each."""
    states = jax.jit(jax.vmap(envs[0].reset))(jax.random.split(jax.random.PRNGKey(0), BATCH))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (BATCH, 6), minval=-1.0, maxval=1.0)
    return states, actions


def _move(env, states, actions, open_to=None):
    def one(state, a, o):
        return env.move(state, a[:3] * env.max_dp, a[3:] * env.max_drot, o)

    opens = None if open_to is None else jnp.full(BATCH, open_to, jnp.float32)
    return jax.jit(jax.vmap(one, in_axes=(0, 0, None if opens is None else 0)))(states, actions, opens)


def _room(env, states, to_deg):
    """Each row's opening sweep from where its jaws are to ``to_deg``, at its pose [m]."""

    def one(es):
        placed = env._place_others(es.needle_pos, es.needle_quat)
        return env._sweep(placed, es.ee_pos, es.ee_quat, es.jaw_deg, jnp.float32(to_deg))

    return np.asarray(jax.jit(jax.vmap(one))(states.pipeline_state))


def test_distances_at_an_opening_are_the_scene_built_at_it():
    scene = load_scene()
    key = jax.random.PRNGKey(2)
    needle = jnp.concatenate([jnp.zeros(3), jnp.array([1.0, 0.0, 0.0, 0.0])])
    for deg in (20.0, 37.5, 80.0):
        wide = load_scene(SceneConfig(jaw_angle_deg=deg)).distance_fn()
        pos = jax.random.uniform(key, (64, 3), minval=-0.012, maxval=0.012)
        quat = jax.random.normal(jax.random.fold_in(key, 1), (64, 4))
        quat = quat / jnp.linalg.norm(quat, axis=1, keepdims=True)
        turned = jax.vmap(scene.distance_fn(), in_axes=(None, None, 0, 0, None, None, None))
        built = jax.vmap(wide, in_axes=(None, None, 0, 0))
        got = turned(needle[:3], needle[3:], pos, quat, None, None, jnp.float32(deg))
        np.testing.assert_allclose(got, built(needle[:3], needle[3:], pos, quat), atol=2e-7)
    # at the scene's own opening the tool's capsules are the constants themselves, bit for bit
    f = scene.distance_fn()
    np.testing.assert_array_equal(
        f(needle[:3], needle[3:], pos[0], quat[0], jaw_deg=jnp.float32(20.0)),
        f(needle[:3], needle[3:], pos[0], quat[0]),
    )


def test_a_step_that_opens_moves_as_the_wide_scene_and_a_blocked_sweep_collides(envs, problems):
    narrow, wide, _ = envs
    states, actions = problems
    room = _room(narrow, states, 60.0)
    assert 0.1 < (room < 0.0).mean() < 0.6  # starts beside the jaws (drawn for 20 degrees) and starts with room
    opened = _move(narrow, states, actions, open_to=60.0)
    at60 = states.replace(pipeline_state=states.pipeline_state.replace(jaw_deg=jnp.full(BATCH, 60.0, jnp.float32)))
    built = _move(wide, at60, actions)
    hit = np.asarray(opened.metrics["collision"]) > 0
    clear = room >= 0.0
    np.testing.assert_array_equal(hit[clear], np.asarray(built.metrics["collision"])[clear] > 0)
    assert hit[~clear].all()  # the sweep into the needle or the grasping tool is a collision
    np.testing.assert_allclose(
        np.asarray(opened.metrics["clearance_mm"])[clear], np.asarray(built.metrics["clearance_mm"])[clear], atol=1e-4
    )
    np.testing.assert_array_equal(np.asarray(opened.pipeline_state.jaw_deg), 60.0)
    # asked to open no wider than it is: the scene's own step, verdict for verdict
    same = _move(narrow, states, actions, open_to=20.0)
    np.testing.assert_array_equal(same.metrics["collision"], _move(narrow, states, actions).metrics["collision"])


def test_the_environments_rule_opens_once_the_sweep_keeps_its_margin(envs, problems):
    narrow, wide, opens = envs
    states, actions = problems
    room = _room(narrow, states, 60.0)
    moved = _move(opens, states, actions)
    jaw_deg = np.asarray(moved.pipeline_state.jaw_deg)
    roomy = room >= opens.jaw_margin
    np.testing.assert_array_equal(jaw_deg, np.where(roomy, 60.0, 20.0))
    assert 0.2 < roomy.mean() < 0.9
    hit = np.asarray(moved.metrics["collision"]) > 0
    np.testing.assert_array_equal(
        hit[~roomy], np.asarray(_move(narrow, states, actions).metrics["collision"])[~roomy] > 0
    )
    at60 = states.replace(pipeline_state=states.pipeline_state.replace(jaw_deg=jnp.full(BATCH, 60.0, jnp.float32)))
    np.testing.assert_array_equal(hit[roomy], np.asarray(_move(wide, at60, actions).metrics["collision"])[roomy] > 0)
    # opened stays opened: a second step does not test the sweep again
    again = _move(opens, moved, actions)
    assert (np.asarray(again.pipeline_state.jaw_deg)[roomy] == 60.0).all()


def test_the_sweep_inside_a_step_is_proved_between_its_check_points():
    """A wire 5 um into the tip's path between two of the environment's check points (20 to 32 degrees
    in 3 intervals: 20, 24, 28, 32; the wire at 26) is caught by the slack, as the host check's."""
    from tests.test_jaw import _wire_past_the_tip

    scene = load_scene()
    sweep = jaw.sweep_fn(scene, steps=3)
    others = scene.motion_distance_fn()[0]
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    for gap, clear in ((-5e-6, False), (1e-4 + jaw.jaw_reach(scene) * math.radians(4.0) / 4.0, True)):
        needle, ee = _wire_past_the_tip(scene, 26.0, gap)
        placed = others(f32(needle[:3]), f32(needle[3:]))
        room = float(sweep(placed, f32(ee[:3]), f32(ee[3:]), jnp.float32(20.0), jnp.float32(32.0)))
        assert (room >= 0.0) == clear


def test_the_kernel_turns_each_lanes_jaws_as_the_xla_walk(envs, problems, monkeypatch):
    """Lanes at 20, 40 and 60 degrees, every lane pending: the kernel's verdicts (Pallas's interpreter)
    are the XLA walk's with the same openings, lane by lane, and differ from a kernel that keeps the
    scene's jaws."""
    monkeypatch.setattr(walk_kernel, "KERNEL", False)
    narrow = envs[0]
    frames = narrow.scene.capsule_frames
    levers = np.asarray(narrow.levers)
    turning = walk_kernel.make_kernel(
        frames.tool_ends, frames.tool_radii, levers, narrow.clearance, jaw_sides=frames.jaw_sides
    )
    fixed = walk_kernel.make_kernel(frames.tool_ends, frames.tool_radii, levers, narrow.clearance)
    states, actions = problems
    degs = jnp.asarray(np.resize([20.0, 40.0, 60.0], BATCH), jnp.float32)

    def lane(es, a, deg):
        dp, rotvec = a[:3] * narrow.max_dp, a[3:] * narrow.max_drot
        placed = narrow._place_others(es.needle_pos, es.needle_quat)
        fastest = jnp.max(jnp.linalg.norm(dp) + jnp.linalg.norm(rotvec) * narrow.levers)
        motion = (placed, es.ee_pos, es.ee_quat, dp, rotvec, deg)
        xla = continuous_walk.motion_collides(narrow._bounds_along, motion, fastest, narrow.clearance)
        radii = jnp.broadcast_to(placed[1], placed[0].shape[1:2])
        return xla, placed[0][0], radii, dp, rotvec, fastest

    xla, ends, radii, dp, rotvec, fastest = jax.jit(jax.vmap(lane))(states.pipeline_state, actions, degs)
    es = states.pipeline_state
    args = (ends, radii, es.ee_pos, es.ee_quat, dp, rotvec, fastest, jnp.ones(BATCH, jnp.bool_))
    half = jnp.radians(degs - 20.0) / 2.0
    turned = np.asarray(walk_kernel.walk_tests(turning, *args, half, interpret=True)[0])
    kept = np.asarray(walk_kernel.walk_tests(fixed, *args, interpret=True)[0])
    np.testing.assert_array_equal(turned, np.asarray(xla))
    assert (turned != kept).sum() > 0 and (turned[np.asarray(degs) == 20.0] == kept[np.asarray(degs) == 20.0]).all()


def test_bad_jaw_openings_are_refused():
    for value in (20.0, 10.0, 81.0, float("nan"), "60"):
        with pytest.raises(ConfigError, match="jaw_open_deg"):
            EnvConfig(jaw_open_deg=value)
    with pytest.raises(ConfigError, match="jaw_open_margin_mm"):
        EnvConfig(jaw_open_deg=60.0, jaw_open_margin_mm=0.1, clearance_mm=0.2)
    assert dataclasses.replace(EnvConfig(), jaw_open_deg=80.0).jaw_open_deg == 80.0
    assert EnvConfig(clearance_mm=1.0).clearance_mm == 1.0  # jaws that stay: any clearance as before


def test_view_sd_by_hand():
    from regrasp_mjx.envs.camera_errors import CameraErrors, Tracking, view_sd_mm

    # tools: white 0.5 mm, 5 deg per mm, one frame; depth 2: each tool 0.25 mm^2 per axis, times
    # (4 + (rad(5) * lever_mm)^2) at its lever (the jaws' 9.6 mm, the grasping tool's 12 mm)
    camera = CameraErrors(Tracking(), Tracking(white_mm=0.5, deg_per_mm=5.0), depth_factor=2.0)
    n = np.asarray(camera.numbers(), np.float32)
    turn = math.radians(5.0)
    want = math.sqrt(0.25 * (4.0 + (turn * 9.6) ** 2) + 0.25 * (4.0 + (turn * 12.0) ** 2))
    got = view_sd_mm(jnp.float32(1.0), n[:5], n[5:10], n[10], 9.6e-3, 5.4e-3, jnp.array([[0.012, 0.0, 0.0]]))
    assert float(got[0]) == pytest.approx(want, rel=1e-5)
    # a needle bias of 1 mm: its spread over three axes, at the needle's radius, whatever the frames
    camera = CameraErrors(Tracking(bias_mm=1.0, deg_per_mm=2.0), Tracking(), depth_factor=1.0)
    n = np.asarray(camera.numbers(), np.float32)
    want = math.sqrt((1.0 + (math.radians(2.0) * 5.4) ** 2) / 3.0)
    got = view_sd_mm(jnp.float32(60.0), n[:5], n[5:10], n[10], 9.6e-3, 5.4e-3, jnp.array([[0.012, 0.0, 0.0]]))
    assert float(got[0]) == pytest.approx(want, rel=1e-5)


@pytest.fixture(scope="module")
def opening_policy():
    from regrasp_mjx.inference.policy import load_policy

    return load_policy().with_env(jaw_open_deg=40.0)


def test_the_loop_opens_on_the_way_where_its_view_leaves_room(opening_policy, paper_testset):
    """Exact views: the loop's decisions are the truth's, with the environment's margin: every opening
    sweep keeps it on the true poses at the step it was made before, none collides, and a row's jaws
    are wide exactly where it opened."""
    from regrasp_mjx.world.sampling import episode_poses

    policy = opening_policy
    needle, start, goal = (x[:24] for x in episode_poses(paper_testset[0]))
    r = policy.execute(needle, start, goal, seed=0, jaw_sigmas=0.0)
    opened = r["opened_at"] >= 0
    assert 0.5 < opened.mean() and not r["opening_collision"].any()
    np.testing.assert_array_equal(r["jaw_deg"], np.where(opened, 40.0, 20.0))
    env = RegraspEnv(policy.env_config)
    rows = np.flatnonzero(opened)
    at = r["poses"][rows, r["opened_at"][rows]]
    from regrasp_mjx.world.sampling import Episode

    episode = Episode.from_poses(*(jnp.asarray(x[rows], jnp.float32) for x in (needle, at, goal)))
    es = jax.vmap(env.reset_from)(episode).pipeline_state
    room = np.asarray(jax.vmap(env.opening_room, in_axes=(0, None))(es, 40.0))
    assert (room >= env.jaw_margin - 1e-6).all()
    assert r["success"].mean() > 0.8
    # the widest opening before the first move is the other design: refused for such a policy
    with pytest.raises(ConfigError, match="on the way"):
        policy.execute(needle, start, goal, jaw_deg=30.0)


@pytest.mark.slow  # an executor and a planner compiled on the CPU: the long tier
def test_a_view_that_misjudges_the_room_is_judged_on_the_truth(opening_policy, paper_testset):
    """Large view errors and no margin in them: sweeps the truth does not prove clear are collisions."""
    from regrasp_mjx.world.sampling import episode_poses

    needle, start, goal = (x[:48] for x in episode_poses(paper_testset[0]))
    r = opening_policy.execute(needle, start, goal, seed=2, camera="lab-typical", jaw_sigmas=0.0)
    assert r["opening_collision"].any()
    assert (r["collision"] | ~r["opening_collision"]).all() and not (r["success"] & r["opening_collision"]).any()


@pytest.mark.slow  # an executor and a planner compiled on the CPU: the long tier
def test_a_plans_opening_step_is_the_one_its_rollout_took(opening_policy, paper_testset):
    """``jaw_opening.opening_steps`` on ``Policy.plan``'s poses names the step the environment opened
    the jaws before: the executor reproducing the plans (one exact frame, stop at the task's
    tolerance) records the same steps."""
    from regrasp_mjx.inference import jaw_opening
    from regrasp_mjx.world.sampling import episode_poses

    needle, start, goal = (x[:16] for x in episode_poses(paper_testset[0]))
    plan = opening_policy.plan(needle, start, goal)
    steps = jaw_opening.opening_steps(opening_policy, needle, plan.poses, plan.steps)
    r = opening_policy.execute(needle, start, goal, frames="one", stop_tolerance=1.0, jaw_sigmas=0.0)
    np.testing.assert_array_equal(r["success"], plan.success)
    np.testing.assert_array_equal(steps, r["opened_at"])
    assert (steps >= 0).mean() > 0.5
    with pytest.raises(ConfigError, match="on the way"):
        from regrasp_mjx.inference.policy import load_policy

        jaw_opening.opening_steps(load_policy("student_v3"), needle, plan.poses, plan.steps)  # its jaws stay
