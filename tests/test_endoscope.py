"""The endoscope's camera model without rendering: its numbers, a hand-worked projection, stereo disparity,
the rig's jitter, the keypoints, visibility on made-up images, the randomisation draws and the image
degradation, that its picture model leaves the collision scene as it was, and that it draws the regrasping
jaws at the opening asked (where a scene of that opening has them, its tips' keypoints with them)."""

from __future__ import annotations

import math

import jax
import mujoco
import numpy as np
import pytest

from regrasp_mjx.core.config import SceneConfig
from regrasp_mjx.envs.camera_errors import depth_axis
from regrasp_mjx.world import domain_randomisation as dr
from regrasp_mjx.world import endoscope
from regrasp_mjx.world.endoscope_scene import CAMERAS, CLASSES, TISSUE_GROUP, endoscope_model
from regrasp_mjx.world.scene import load_scene


def test_the_rig_s_numbers():
    full = endoscope.Rig(width=1920, height=1080)
    assert full.focal_px == pytest.approx(960.0 / math.tan(math.radians(35.0)))  # 1371.0 px
    assert full.focal_px == pytest.approx(1371.0, abs=0.1)
    np.testing.assert_allclose(full.intrinsics(), [[1371.02, 0, 959.5], [0, 1371.02, 539.5], [0, 0, 1]], atol=0.01)
    rig = endoscope.Rig()
    assert (rig.width, rig.height, rig.baseline_m, rig.working_distance_m) == (320, 180, 0.005, 0.05)
    assert math.tan(math.radians(rig.fovy_deg) / 2) == pytest.approx(90.0 / rig.focal_px)
    assert rig.focal_px == pytest.approx(full.focal_px / 6)  # the intrinsics scale with the size
    # at the working distance: disparity f B / Z (137 px at 1080p) and the view's width (70 mm)
    assert full.focal_px * 0.005 / 0.05 == pytest.approx(137.1, abs=0.1)
    assert 2 * 0.05 * math.tan(math.radians(35.0)) == pytest.approx(0.070, abs=1e-3)
    for bad in ({"width": 8}, {"baseline_m": 0.0}, {"hfov_deg": 180.0}, {"view_axis": (0.0, 0.0, 1.0)}):
        with pytest.raises(ValueError):
            endoscope.Rig(**bad)


def test_the_rig_looks_along_the_scene_camera_s_axis_at_the_workspace():
    rig = endoscope.Rig()
    rot, centre = rig.frame()
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    np.testing.assert_allclose(rot[:, 2], depth_axis(), atol=1e-6)  # camera_errors' depth axis is its optical axis
    np.testing.assert_allclose(centre + rig.working_distance_m * rot[:, 2], rig.look_at_m, atol=1e-12)
    # the image's x axis is e_g's z (the tools' shafts) turned by the roll about the optical axis
    ez = np.array([0.0, 0.0, 1.0])
    x0 = endoscope.unit(ez - (ez @ rot[:, 2]) * rot[:, 2])
    assert math.degrees(math.acos(rot[:, 0] @ x0)) == pytest.approx(rig.roll_deg)
    poses = endoscope.camera_poses(rig)
    assert poses.shape == (2, 4, 4)
    np.testing.assert_allclose(poses[1, :3, 3] - poses[0, :3, 3], rig.baseline_m * rot[:, 0], atol=1e-15)
    np.testing.assert_allclose(poses[:, :3, 3].mean(axis=0), centre, atol=1e-15)
    np.testing.assert_allclose(endoscope.invert(poses) @ poses, np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-12)


def test_a_hand_worked_projection_and_the_stereo_disparity():
    """A point 2 mm right of, 1 mm below and 40 mm in front of the left camera (its own frame) lands
    on u = cx + f 2/40, v = cy + f 1/40 in the left image; the right camera, 5 mm to the right, sees
    it f B / Z = f 5/40 pixels to the left, on the same row."""
    rig = endoscope.Rig()
    k, f = rig.intrinsics(), rig.focal_px
    left = endoscope.camera_poses(rig)[0]
    point = left[:3, :3] @ np.array([0.002, 0.001, 0.040]) + left[:3, 3]
    uv, z = endoscope.project(point[None, None], endoscope.invert(endoscope.camera_poses(rig)), k)
    assert uv.shape == (2, 1, 2) and z.shape == (2, 1)
    np.testing.assert_allclose(z, 0.040, atol=1e-12)
    np.testing.assert_allclose(uv[0, 0], [159.5 + f * 0.05, 89.5 + f * 0.025], atol=1e-9)
    np.testing.assert_allclose(uv[0, 0, 0] - uv[1, 0, 0], f * 0.005 / 0.040, atol=1e-9)
    assert uv[1, 0, 1] == pytest.approx(uv[0, 0, 1], abs=1e-9)
    # the look-at point is on the rig's axis: in each image half the disparity from the centre
    uv, z = endoscope.project(np.array(rig.look_at_m)[None], endoscope.invert(endoscope.camera_poses(rig)), k)
    np.testing.assert_allclose(z, 0.05, atol=1e-12)
    np.testing.assert_allclose(uv[:, 0, 0], [159.5 + f * 0.0025 / 0.05, 159.5 - f * 0.0025 / 0.05], atol=1e-9)


def test_jitter_turns_the_rig_about_its_centre_and_shifts_it():
    rig = endoscope.Rig()
    rot, centre = rig.frame()
    shift = np.array([[0.001, -0.002, 0.003], [0.0, 0.0, 0.0]])
    rotvec = np.array([[0.0, 0.0, 0.0], [0.01, 0.02, -0.03]])
    poses = endoscope.camera_poses(rig, shift, rotvec)
    assert poses.shape == (2, 2, 4, 4)
    np.testing.assert_allclose(poses[0, :, :3, :3], np.broadcast_to(rot, (2, 3, 3)), atol=1e-15)
    np.testing.assert_allclose(poses[0, :, :3, 3].mean(axis=0), centre + shift[0], atol=1e-15)
    turn = poses[1, 0, :3, :3] @ rot.T
    assert math.acos((np.trace(turn) - 1) / 2) == pytest.approx(np.linalg.norm(rotvec[1]), rel=1e-9)
    np.testing.assert_allclose(poses[1, :, :3, 3].mean(axis=0), centre, atol=1e-15)
    np.testing.assert_allclose(endoscope.rotation_matrix(rotvec[1]), turn, atol=1e-12)


def test_the_keypoints():
    scene = load_scene()
    kp = endoscope.keypoints(scene)
    r = scene.config.needle_radius_mm * 1e-3
    assert len(kp.names) == endoscope.N_ARC + 6 and kp.names[0] == "needle_arc0"
    np.testing.assert_allclose(kp.local[0], [0, 0, r], atol=1e-15)  # the tip, alpha = pi/2
    np.testing.assert_allclose(kp.local[endoscope.N_ARC - 1], [0, 0, -r], atol=1e-15)  # the tail
    np.testing.assert_allclose(np.linalg.norm(kp.local[: endoscope.N_ARC], axis=1), r)
    for tool, opening in (("grasp", 2 * 6.6868), ("regrasp", scene.config.jaw_angle_deg)):
        a, b = (kp.local[kp.names.index(f"{tool}_jaw_{s}_tip")] for s in ("a", "b"))
        np.testing.assert_allclose(np.linalg.norm([a, b], axis=1), 0.0102, atol=2e-7)  # the LND's 10.2 mm jaws
        assert math.degrees(math.acos(a @ b / (a @ a))) == pytest.approx(opening, abs=1e-3)
        np.testing.assert_allclose(kp.local[kp.names.index(f"{tool}_pivot")], 0.0)
    needle = np.array([[0.001, 0.002, 0.003, 0.0, 1.0, 0.0, 0.0]])  # 180 deg about x
    ee = np.array([[0.01, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    world = kp.world(needle, ee)
    np.testing.assert_allclose(world[0, 0], [0.001, 0.002, 0.003 - r], atol=1e-15)
    np.testing.assert_allclose(world[0, kp.obj == 1], kp.local[kp.obj == 1])  # e_g is the grasping tool
    np.testing.assert_allclose(world[0, kp.obj == 2], kp.local[kp.obj == 2] + [0.01, 0, 0])


def test_visibility_on_made_up_images():
    depth = np.full((1, 10, 12), 0.1)
    classes = np.ones((1, 10, 12), np.int8)
    depth[0, 4:6, 5:7], classes[0, 4:6, 5:7] = 0.05, 2  # an object at 50 mm
    uv = np.array([[[5.2, 4.9], [5.2, 4.9], [5.2, 4.9], [20.0, 4.0], [1.0, 1.0], [5.2, 4.9]]])
    z = np.array([[0.0502, 0.0502, 0.06, 0.05, 0.0502, -0.05]])
    want = np.array([2, 3, 2, 2, 2, 2])  # the second is another object's point: something else is seen there
    slack = np.full(6, 2.5e-4)
    seen = endoscope.visible(uv, z, depth, classes, want, slack)
    # seen; not its object; behind a nearer part of its own object; outside; nothing of it near; behind the camera
    np.testing.assert_array_equal(seen, [[True, False, False, False, False, False]])
    assert endoscope.visible(uv[0], z[0], depth[0], classes[0], want, slack).shape == (6,)


def test_draws_are_a_pure_function_of_each_seed():
    a, b = dr.draws([3, 7, 11]), dr.draws([7])
    for x, y in zip(jax.tree.leaves(a.row(1)), jax.tree.leaves(b.row(0))):
        np.testing.assert_array_equal(x, y)  # a row does not depend on the batch
    for x, y in zip(jax.tree.leaves(dr.draws([3])), jax.tree.leaves(a.row(slice(0, 1)))):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a.row(0).tissue_rgb, a.row(1).tissue_rgb)
    with pytest.raises(ValueError, match="seeds"):
        dr.draws([-1])
    with pytest.raises(ValueError, match="seeds"):
        dr.draws([0.5])


def test_draws_stay_in_their_ranges():
    d = dr.draws(np.arange(400))
    shift = np.linalg.norm(np.asarray(d.camera_shift), axis=1) * 1e3
    assert shift.max() <= endoscope.CALIBRATION_MM + 1e-6 and shift.max() > 0.8 * endoscope.CALIBRATION_MM
    turn = dr.turn_deg(d)
    assert turn.max() <= endoscope.CALIBRATION_DEG + 1e-6 and turn.max() > 0.8 * endoscope.CALIBRATION_DEG
    assert np.all(np.abs(np.asarray(d.light_offset)) <= 0.01 + 1e-9)
    for name in ("needle_rgb", "jaw_rgb", "shaft_rgb", "tissue_rgb"):
        x = np.asarray(getattr(d, name))
        assert x.shape == (400, 3) and x.min() >= 0.0 and x.max() <= 1.0
    lo, hi = np.asarray(dr.RANGES["tissue_rgb"])
    assert np.all((np.asarray(d.tissue_rgb) >= lo) & (np.asarray(d.tissue_rgb) <= hi))
    fill = np.asarray(d.fill_dir)
    np.testing.assert_allclose(np.linalg.norm(fill, axis=1), 1.0, atol=1e-5)
    assert np.all(fill @ endoscope.unit(np.array(endoscope.VIEW_AXIS)) >= -1e-6)
    for name in ("blur_px", "noise", "tissue_behind"):
        x, (a, b) = np.asarray(getattr(d, name)), dr.RANGES[{"tissue_behind": "tissue_behind_mm"}.get(name, name)]
        scale = 1e3 if name == "tissue_behind" else 1.0
        assert a <= x.min() * scale and x.max() * scale <= b
    n = dr.nominal(2)
    assert np.asarray(n.camera_shift).shape == (2, 3) and not np.any(n.camera_shift) and not np.any(n.noise)


def test_degrade():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (2, 2, 12, 10, 3), dtype=np.uint8)
    zero, one = np.zeros(2, np.float32), np.ones((2, 3), np.float32)
    keys = dr.noise_keys([1, 2])
    np.testing.assert_array_equal(dr.degrade(images, zero, zero, one, keys), images)  # nothing to do
    flat = np.full((2, 2, 12, 10, 3), 100, np.uint8)
    np.testing.assert_array_equal(
        dr.degrade(flat, np.full(2, 0.8, np.float32), zero, one, keys), flat
    )  # blur keeps a flat image
    blurred = np.asarray(dr.degrade(images, np.full(2, 0.8, np.float32), zero, one, keys))
    assert blurred.astype(float).std() < images.astype(float).std()
    noise = np.full(2, 0.02, np.float32)
    a = np.asarray(dr.degrade(flat, zero, noise, one, keys))
    assert a.astype(float).std() == pytest.approx(0.02 * 255, rel=0.15)
    np.testing.assert_array_equal(a, dr.degrade(flat, zero, noise, one, dr.noise_keys([1, 2])))  # same keys
    assert not np.array_equal(a, dr.degrade(flat, zero, noise, one, dr.noise_keys([1, 2], frame=1)))
    assert not np.array_equal(a[0, 0], a[0, 1])  # each camera its own noise
    np.testing.assert_array_equal(dr.degrade(flat, zero, zero, np.full((2, 3), 1.1, np.float32), keys), 110)


def test_the_picture_model_leaves_the_collision_scene_as_it_was():
    scene = load_scene()
    before = {k: np.copy(getattr(scene.model, k)) for k in ("geom_size", "geom_pos", "geom_quat", "geom_contype")}
    axis = depth_axis().copy()
    endo = endoscope_model(scene)
    m, r = endo.model, scene.render_model
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(scene.model, k), v)
    np.testing.assert_array_equal(depth_axis(), axis)
    collide = lambda mm: {  # noqa: E731
        mm.geom(i).name: (mm.geom_size[i], mm.geom_pos[i], mm.geom_quat[i], mm.geom_contype[i], mm.geom_conaffinity[i])
        for i in range(mm.ngeom)
        if mm.geom_contype[i] or mm.geom_conaffinity[i]
    }
    ours, theirs = collide(m), collide(r)
    assert sorted(ours) == sorted(theirs) and len(ours) == len(scene.model.geom_size)
    for name, values in theirs.items():
        for x, y in zip(ours[name], values):
            np.testing.assert_array_equal(x, y, err_msg=name)
    tissue = m.geom("tissue")
    assert tissue.contype[0] == tissue.conaffinity[0] == 0 and tissue.group[0] == TISSUE_GROUP
    assert TISSUE_GROUP not in set(r.geom_group[(r.geom_contype > 0) | (r.geom_conaffinity > 0)])
    assert m.ncam == 2 and [m.camera(i).name for i in range(2)] == list(CAMERAS)
    np.testing.assert_allclose(m.cam_fovy, endo.rig.fovy_deg)
    assert CLASSES[endo.classes[m.geom("needle_visual").id]] == "needle"
    assert CLASSES[endo.classes[m.geom("regrasp_shaft").id]] == "regrasping_tool"
    assert CLASSES[endo.classes[m.geom("grasp_jaw_a_visual").id]] == "grasping_tool"
    # the cameras are where camera_poses puts them, MuJoCo's axes (looking along -z, y up) from OpenCV's
    d = dr.draws([5]).row(0)
    poses = endo.apply(d)
    np.testing.assert_allclose(poses, endoscope.camera_poses(endo.rig, d.camera_shift, d.camera_rotvec))
    for cam, pose in zip(endo.cameras, poses):
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.cam_quat[cam])
        np.testing.assert_allclose(rot.reshape(3, 3) @ np.diag([1.0, -1.0, -1.0]), pose[:3, :3], atol=1e-9)
        np.testing.assert_allclose(m.cam_pos[cam], pose[:3, 3])


def _jaw_opening_deg(model: mujoco.MjModel, data: mujoco.MjData, tool: str) -> float:
    """The angle between a tool's two jaw meshes as placed in ``data`` (each turned about the hinge)."""
    a, b = (data.geom_xmat[model.geom(f"{tool}_jaw_{s}_visual").id].reshape(3, 3) for s in ("a", "b"))
    return math.degrees(math.acos(np.clip((np.trace(a @ b.T) - 1.0) / 2.0, -1.0, 1.0)))


def test_the_picture_model_draws_the_regrasping_jaws_at_the_opening_asked():
    """``open_jaws(40)`` on the 20-degree scene's picture model puts each regrasping jaw's mesh and capsule
    where the 40-degree scene's model has them, at any tool pose; None puts them back exactly; the rest
    of the model stays. The 40-degree scene's own meshes are drawn at 40 degrees (the MJCF's euler angles
    no longer override the scene's opening). The keypoints follow: the jaws' tips turned open are the
    40-degree scene's, the other keypoints unmoved."""
    base, wide = endoscope_model(), endoscope_model(SceneConfig(jaw_angle_deg=40.0))
    needle = np.array([0.001, -0.002, 0.003, 1.0, 0.0, 0.0, 0.0])
    quat = np.array([0.8, 0.3, -0.4, 0.33])
    ee = np.concatenate([[0.012, 0.004, -0.006], quat / np.linalg.norm(quat)])
    data = {m: mujoco.MjData(m.model) for m in (base, wide)}

    def place(m, jaw_deg="unset"):
        if jaw_deg != "unset":
            m.open_jaws(jaw_deg)
        data[m].qpos[:] = m.qpos(needle, ee)
        mujoco.mj_kinematics(m.model, data[m])
        return data[m].geom_xpos.copy(), data[m].geom_xmat.copy()

    pos20, mat20 = place(base)
    assert _jaw_opening_deg(base.model, data[base], "regrasp") == pytest.approx(20.0, abs=1e-9)
    pos40, mat40 = place(wide)
    assert _jaw_opening_deg(wide.model, data[wide], "regrasp") == pytest.approx(40.0, abs=1e-9)
    opened_pos, opened_mat = place(base, 40.0)
    assert _jaw_opening_deg(base.model, data[base], "regrasp") == pytest.approx(40.0, abs=1e-9)
    jaws = base.jaw_geoms
    assert sorted(base.model.geom(int(g)).name for g in jaws) == [
        "regrasp_jaw_a",
        "regrasp_jaw_a_visual",
        "regrasp_jaw_b",
        "regrasp_jaw_b_visual",
    ]
    np.testing.assert_allclose(opened_pos[jaws], pos40[jaws], atol=1e-12)
    np.testing.assert_allclose(opened_mat[jaws], mat40[jaws], atol=1e-12)
    assert np.linalg.norm(opened_pos[jaws] - pos20[jaws], axis=-1).min() > 7e-4  # the jaws' middles: 0.8 mm
    rest = np.setdiff1d(np.arange(base.model.ngeom), jaws)
    np.testing.assert_array_equal(opened_pos[rest], pos20[rest])
    np.testing.assert_array_equal(opened_mat[rest], mat20[rest])
    assert _jaw_opening_deg(base.model, data[base], "grasp") == pytest.approx(13.3737, abs=1e-3)  # never opened
    back_pos, back_mat = place(base, None)
    np.testing.assert_array_equal(back_pos, pos20)
    np.testing.assert_array_equal(back_mat, mat20)

    kp20, kp40 = (endoscope.keypoints(m.scene) for m in (base, wide))
    turn = np.radians([10.0, 0.0])  # the first row opened to 40 degrees, the second at the scene's 20
    two = (np.stack([needle, needle]), np.stack([ee, ee]))
    world = kp20.world(*two, turn)
    np.testing.assert_allclose(world[0], kp40.world(*two)[0], atol=1e-15)
    np.testing.assert_allclose(world[1], kp20.world(*two)[1], atol=1e-15)
    moved = np.abs(world[0] - world[1]).max(axis=-1) > 1e-4
    assert [n for n, m in zip(kp20.names, moved) if m] == ["regrasp_jaw_a_tip", "regrasp_jaw_b_tip"]
