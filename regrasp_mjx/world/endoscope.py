"""The stereo endoscope as a camera model: the dVRK's camera pair as numbers (with their sources), its pose
over the workspace, and the pinhole projection of the task's keypoints into both images.

The numbers, and where they come from ("ours" where no source gives one; every one a field of
:class:`Rig`):

- **baseline** 5 mm between the two optical centres: the da Vinci's 12 mm stereo endoscope (InSite
  vision system: "3-D imaging through a 12 mm endoscope", Advincula, *Robotics in clinical
  gynecology*) carries two channels 5 mm apart ("existing 3D laparoscopes which use 5-mm camera
  separation", Surg Endosc 22(11):2396-2400, 2008, doi:10.1007/s00464-008-0032-8, a study on a
  surgical telerobot's stereo laparoscope).
- **resolution** 1920 x 1080 per eye: the paper's dVRK stereo endoscope is "1080p and run at 30fps"
  (§V-C); the dVRK documentation lists the Classic SD endoscope (640 x 480), the S HD (same
  endoscope, 1080i sensors) and the Si HD (jhu-dvrk/dvrk-readthedocs, ``docs/pages/video/``).
  Images are rendered smaller (:data:`RESOLUTION`, ours); the intrinsics scale with the size.
- **field of view** 70 degrees across the image (horizontal; ours): "Typically, the angle of view
  [of a laparoscope] is about 70 degrees" (a study of the perspective effect of laparoscopes'
  wide-angle lenses); the Surgical Robotics Challenge's dVRK endoscope model uses 1.2 rad vertical
  at 640 x 480 (surgical-robotics-ai/surgical_robotics_challenge, ``ADF/world/world_stereo.yaml``).
  At 1920 x 1080 that is a focal length of 1371 px.
- **working distance** 50 mm from the rig's centre to the point it looks at (ours): suturing is
  seen close up; the Surgical Robotics Challenge places its needle 80-200 mm from the endoscope for
  finding it in a wide view. At 50 mm the view is 70 mm wide, the 10.8 mm needle about 300 px at
  1080p, and a point's disparity 137 px.
- **parallel optical axes** (ours): what a rectified stereo pair gives; disparity is
  ``f * baseline / depth``.
- **where it looks** (ours): along the scene's ``overview`` camera's axis (:data:`VIEW_AXIS`, which
  is also the depth axis of :mod:`regrasp_mjx.envs.camera_errors`), at :data:`LOOK_AT_M`, a point
  between the paper300 needles' centres (mean 0.0, -4.6, 7.4 mm in e_g) and the regrasping tool's
  starts (5.7, -7.7, 15.5 mm); rolled so that the tools' shafts (the e_g z axis) cross the image
  :data:`ROLL_DEG` from its horizontal.
- **jitter** of the rig's pose per episode, within the calibration sizes of SPEC "Errors of a lab":
  a shift of up to :data:`CALIBRATION_MM` in a random direction and a rotation of up to
  :data:`CALIBRATION_DEG` about a random axis through the rig's centre (the sizes of
  ``NeedleRegraspCalibration``; ArUco hand-eye registration is 5-10 mm on the dVRK).

Conventions: camera frames are OpenCV's (x right, y down, z forward along the optical axis); a
camera's extrinsics are the world-to-camera transform (the world is e_g); pixel coordinates
``(u, v)`` have the centre of the top-left pixel at ``(0, 0)``, so pixel ``(i, j)`` (column,
row) covers ``u`` in ``[i - 0.5, i + 0.5)``. Poses are 7-vectors ``[x, y, z, qw, qx, qy, qz]`` (m).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from regrasp_mjx.world.distances import turn_jaws
from regrasp_mjx.world.scene import Scene

BASELINE_M = 0.005
HFOV_DEG = 70.0
FULL_RESOLUTION = (1920, 1080)
RESOLUTION = (320, 180)  # rendered (ours): 16:9 like the endoscope, 0.22 mm per pixel at 50 mm
WORKING_DISTANCE_M = 0.050
VIEW_AXIS = (0.74836024, 0.4929319, -0.44381876)  # the MJCF's overview camera looks along this (e_g)
LOOK_AT_M = (0.003, -0.006, 0.011)
ROLL_DEG = 30.0
CALIBRATION_MM = 5.0
CALIBRATION_DEG = 3.0
N_ARC = 9  # needle keypoints along the arc, tip to tail
OBJECTS = ("needle", "grasping_tool", "regrasping_tool")  # a keypoint's object, the order of poses
WRIST_RADIUS_M = 0.002  # the clevis capsule around each pivot (models/regrasp_scene.xml)


@dataclasses.dataclass(frozen=True)
class Rig:
    """The stereo pair (see the module docstring for the numbers).

    Attributes:
      width, height: the rendered image size in pixels (both cameras).
      baseline_m: distance between the two optical centres, along the image x axis.
      hfov_deg: the angle of view across the image's width.
      working_distance_m: from the rig's centre to ``look_at_m``.
      look_at_m: the point the rig looks at, in e_g.
      view_axis: the optical axis in e_g (normalised here).
      roll_deg: the image's x axis, turned by this from the projection of e_g's z axis.
    """

    width: int = RESOLUTION[0]
    height: int = RESOLUTION[1]
    baseline_m: float = BASELINE_M
    hfov_deg: float = HFOV_DEG
    working_distance_m: float = WORKING_DISTANCE_M
    look_at_m: tuple[float, float, float] = LOOK_AT_M
    view_axis: tuple[float, float, float] = VIEW_AXIS
    roll_deg: float = ROLL_DEG

    def __post_init__(self) -> None:
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ValueError(f"width and height must be within [16, 4096] pixels, got {self.width} x {self.height}")
        if not 0.0 < self.baseline_m <= 0.05:
            raise ValueError(f"baseline_m must be in (0, 0.05] m, got {self.baseline_m}")
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"hfov_deg must be in [1, 170] degrees, got {self.hfov_deg}")
        if not 0.005 <= self.working_distance_m <= 0.5:
            raise ValueError(f"working_distance_m must be in [0.005, 0.5] m, got {self.working_distance_m}")
        axis = np.asarray(self.view_axis, np.float64)
        if axis.shape != (3,) or not np.linalg.norm(axis) > 0 or abs(unit(axis)[2]) > 0.999:
            raise ValueError(f"view_axis must be a 3-vector not along e_g's z axis, got {self.view_axis}")

    @property
    def focal_px(self) -> float:
        """The focal length in pixels (square pixels): ``(width / 2) / tan(hfov / 2)``."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fovy_deg(self) -> float:
        """The vertical angle of view (MuJoCo's camera ``fovy``) that this focal length gives."""
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.focal_px))

    def intrinsics(self) -> np.ndarray:
        """The 3 x 3 camera matrix ``K`` (both cameras; OpenCV's convention, the principal point at
        the image centre: ``((width - 1) / 2, (height - 1) / 2)``)."""
        f = self.focal_px
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """The rig's nominal frame in e_g: its rotation (columns x right, y down, z along the optical
        axis) and its centre, midway between the two cameras."""
        z = unit(np.asarray(self.view_axis, np.float64))
        ez = np.array([0.0, 0.0, 1.0])
        x0 = unit(ez - (ez @ z) * z)
        roll = math.radians(self.roll_deg)
        x = math.cos(roll) * x0 + math.sin(roll) * np.cross(z, x0)
        rot = np.stack([x, np.cross(z, x), z], axis=1)
        return rot, np.asarray(self.look_at_m, np.float64) - self.working_distance_m * z


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` ``[..., 3]`` scaled to unit length along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` of rotation vectors ``[..., 3]`` (radians; Rodrigues)."""
    rotvec = np.asarray(rotvec, np.float64)
    angle = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = rotvec / np.maximum(np.linalg.norm(rotvec, axis=-1, keepdims=True), 1e-300)
    cross = np.zeros(rotvec.shape[:-1] + (3, 3))
    cross[..., 0, 1], cross[..., 0, 2], cross[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    cross = cross - np.swapaxes(cross, -1, -2)
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def quat_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` of unit quaternions ``[..., 4]`` (wxyz)."""
    w, x, y, z = np.moveaxis(np.asarray(quat, np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def camera_poses(rig: Rig, shift_m=None, rotvec=None) -> np.ndarray:
    """Both cameras' poses in e_g, ``[..., 2, 4, 4]`` camera-to-world (left, right; OpenCV axes):
    the rig's nominal frame turned by ``rotvec`` ``[..., 3]`` (radians) about its centre and moved by
    ``shift_m`` ``[..., 3]`` (the per-episode jitter; None: none), each camera half the baseline from
    the centre along the rig's x axis (the left one on -x)."""
    rot, centre = rig.frame()
    shift = np.zeros(3) if shift_m is None else np.asarray(shift_m, np.float64)
    turn = rotation_matrix(np.zeros(3) if rotvec is None else rotvec)
    batch = np.broadcast_shapes(shift.shape[:-1], turn.shape[:-2])
    rot = np.broadcast_to(turn @ rot, batch + (3, 3))
    centre = np.broadcast_to(centre + shift, batch + (3,))
    out = np.zeros(batch + (2, 4, 4))
    out[..., :3, :3] = rot[..., None, :, :]
    for i, side in enumerate((-0.5, 0.5)):
        out[..., i, :3, 3] = centre + side * rig.baseline_m * rot[..., :, 0]
    out[..., 3, 3] = 1.0
    return out


def invert(pose: np.ndarray) -> np.ndarray:
    """The inverse of rigid transforms ``[..., 4, 4]``."""
    out = np.zeros_like(pose)
    rt = np.swapaxes(pose[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ pose[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def project(points: np.ndarray, world_to_camera: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[..., K, 2]`` (u, v) and depths ``[..., K]`` (the camera-frame z, m) of
    points ``[..., K, 3]`` in e_g seen by cameras ``world_to_camera`` ``[..., 4, 4]`` with the camera
    matrix ``k`` (3 x 3). Points behind a camera get a negative depth (their pixels mean nothing)."""
    cam = np.einsum("...ij,...kj->...ki", world_to_camera[..., :3, :3], points) + world_to_camera[..., None, :3, 3]
    z = cam[..., 2]
    uv = np.stack([k[0, 0] * cam[..., 0] / z + k[0, 2], k[1, 1] * cam[..., 1] / z + k[1, 2]], axis=-1)
    return uv, z


@dataclasses.dataclass(frozen=True)
class Keypoints:
    """Named points fixed on the needle and the tools.

    Attributes:
      names: one per keypoint: ``needle_arc0`` (the tip, alpha = pi/2) to ``needle_arc8`` (the
        tail, 3 pi/2), then per tool (``grasp_``, ``regrasp_``) the jaw pivot and each jaw's tip.
      obj: each keypoint's object, an index into :data:`OBJECTS`.
      local: each one's position in its object's frame (n, e_g, e_r) [m].
      depth_slack: how far inside its object's surface it lies at most [m] (the wire's radius, a
        jaw's, the wrist's around a pivot): what visibility allows between it and the surface seen.
    """

    names: tuple[str, ...]
    obj: np.ndarray
    local: np.ndarray
    depth_slack: np.ndarray

    def world(self, needle, ee, jaw_turn=None) -> np.ndarray:
        """The keypoints ``[B, K, 3]`` in e_g for needle and regrasping end-effector poses ``[B, 7]``
        (the grasping tool is e_g itself). ``jaw_turn`` ``[B]`` (rad; None: none): how far each
        regrasping jaw is turned open about the hinge beyond the opening the keypoints were made at
        (half the opening's change): the regrasping jaws' tips turned with it (:func:`turn_open`)."""
        poses = object_poses(needle, ee)
        rot = quat_matrix(poses[:, self.obj, 3:])
        if jaw_turn is None:
            return poses[:, self.obj, :3] + np.einsum("bkij,kj->bki", rot, self.local)
        local = np.repeat(self.local[None], len(poses), axis=0)
        tips = np.array([n.startswith(REGRASP_JAW_PREFIX) for n in self.names])
        local[:, tips] = turn_open(self.local[tips], np.broadcast_to(np.asarray(jaw_turn, np.float64), len(poses)))
        return poses[:, self.obj, :3] + np.einsum("bkij,bkj->bki", rot, local)


REGRASP_JAW_PREFIX = "regrasp_jaw_"  # the regrasping jaws' keypoints (their tips) and geoms


def turn_open(points: np.ndarray, turn) -> np.ndarray:
    """Points fixed on the regrasping jaws ``[n, 3]`` (e_r; each on the side of its jaw: ``+y`` jaw a,
    ``-y`` jaw b) with each jaw turned open about the hinge, the end-effector's x axis, by ``turn``
    ``[B]`` rad (negative: closed), as the environment turns the jaws' capsules
    (:func:`regrasp_mjx.world.distances.turn_jaws`): ``[B, n, 3]``."""
    points = np.asarray(points, np.float64)
    turn = np.atleast_1d(np.asarray(turn, np.float64))[:, None]
    ends = np.broadcast_to(points, (len(turn),) + points.shape)
    return turn_jaws(ends, np.sign(points[:, 1]), turn, np)


def object_poses(needle, ee) -> np.ndarray:
    """``[B, 3, 7]``: the needle, the grasping tool (the identity) and the regrasping tool in e_g."""
    needle = np.atleast_2d(np.asarray(needle, np.float64))
    ee = np.atleast_2d(np.asarray(ee, np.float64))
    grasp = np.broadcast_to([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], needle.shape)
    return np.stack([needle, grasp, ee], axis=1)


def keypoints(scene: Scene, n_arc: int = N_ARC) -> Keypoints:
    """The scene's keypoints: ``n_arc`` points evenly along the needle's arc from the tip to the
    tail (its radius and wire from ``scene.config``), and per tool the jaw pivot (the end-effector
    frame's origin) and each jaw's tip (the far end of the jaw capsule plus its radius: 10.2 mm from
    the pivot, at the scene's opening)."""
    if n_arc < 2:
        raise ValueError(f"n_arc must be >= 2 (the tip and the tail), got {n_arc}")
    radius = scene.config.needle_radius_mm * 1e-3
    alpha = np.linspace(math.pi / 2, 3 * math.pi / 2, n_arc)
    names = [f"needle_arc{i}" for i in range(n_arc)]
    local = [np.stack([np.zeros(n_arc), radius * np.cos(alpha), radius * np.sin(alpha)], axis=1)]
    obj, slack = [0] * n_arc, [scene.config.wire_radius_mm * 1e-3] * n_arc
    for o, prefix, caps in ((1, "grasp", scene.grasp_capsules), (2, "regrasp", scene.regrasp_capsules)):
        by_name = {c.name: c for c in caps}
        names.append(f"{prefix}_pivot")
        local.append(np.zeros((1, 3)))
        obj.append(o)
        slack.append(WRIST_RADIUS_M)
        for side in ("a", "b"):
            cap = by_name[f"{prefix}_jaw_{side}"]
            far = max((cap.p0, cap.p1), key=np.linalg.norm)
            near = cap.p1 if far is cap.p0 else cap.p0
            names.append(f"{prefix}_jaw_{side}_tip")
            local.append((far + cap.radius * unit(far - near))[None])
            obj.append(o)
            slack.append(cap.radius)
    return Keypoints(tuple(names), np.array(obj), np.concatenate(local), np.array(slack))


def visible(
    uv: np.ndarray,
    z: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    want: np.ndarray,
    slack: np.ndarray,
    margin_m: float = 5e-4,
    window: int = 1,
) -> np.ndarray:
    """Which projected keypoints an image shows: ``[..., K]`` bool for pixels ``uv`` ``[..., K, 2]`` at
    depths ``z`` ``[..., K]``, given the image's depth ``[..., H, W]`` (m) and classes ``[..., H, W]``.
    A keypoint is visible when it lies in front of the camera, inside the image, and within
    ``window`` pixels of its pixel some pixel shows its own object (class ``want`` ``[K]``) at a
    depth within ``slack + margin_m`` of its own (``slack`` ``[K]``: how far inside its object's
    surface it lies): its object is seen there, not something in front of it (nor a nearer part of
    its own object). The window allows for a wire thinner than a pixel."""
    h, w = depth.shape[-2:]
    n = int(np.prod(z.shape[:-1], dtype=np.int64))
    zf, depth, classes = z.reshape(n, -1), depth.reshape(n, h, w), classes.reshape(n, h, w)
    col = np.rint(uv[..., 0]).astype(np.int64).reshape(n, -1)
    row = np.rint(uv[..., 1]).astype(np.int64).reshape(n, -1)
    inside = (zf > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    image = np.arange(n)[:, None]
    seen = np.zeros(zf.shape, bool)
    for dr in range(-window, window + 1):
        for dc in range(-window, window + 1):
            r, c = np.clip(row + dr, 0, h - 1), np.clip(col + dc, 0, w - 1)
            d, k = depth[image, r, c], classes[image, r, c]
            seen |= (k == want) & (np.abs(d - zf) <= slack + margin_m)
    return (inside & seen).reshape(z.shape)
