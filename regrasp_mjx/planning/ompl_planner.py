"""OMPL planners in SE(3) over the host collision checker (paper §III-C.1, Table II).

The state is the regrasping end-effector pose in the grasping end-effector frame. A state is valid
when it lies in the planning box and the scene has no counted collision (CPU MuJoCo, the same MJCF
and filtering as the MJX environment; or, with ``checker="lean"``, the same capsule pairs tested by
compiled code, a whole motion per call). A motion between two states is valid only where every pose
along it is proved clear (:mod:`regrasp_mjx.world.continuous`), not at sampled states.

OMPL 2.x (nanobind) Python API: states come from ``space.allocState()``; validity checkers are plain
callables; ``ou.RNG.setSeed`` must be called before any space or planner is built.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from regrasp_mjx.core.config import require, require_numbers
from regrasp_mjx.core.geometry import unit_quaternions
from regrasp_mjx.envs.host import HostChecker
from regrasp_mjx.envs.lean_checker import LeanChecker
from regrasp_mjx.envs.lean_collision import Held

PLANNERS = ("PRMstar", "RRTstar", "BFMTstar", "BITstar", "RRTConnect")
DIRECTIONS = ("forward", "reverse")
CHECKERS = ("mujoco", "lean")


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """How a plan is made.

    Attributes:
      planner: one of PRMstar, RRTstar, BFMTstar, BITstar (the paper's four) or RRTConnect (ours:
        the fast classical anchor; not asymptotically optimal, it returns its first path).
      direction: ``forward`` (start -> goal) or ``reverse`` (goal -> start, path reversed after).
      budget_s: planning time limit; planning stops at the first exact solution or the limit.
      simplify_s: shortcutting of the found path (counted in the planning time); 0 turns it off.
      margin_mm: the planning box is the start/goal bounding box grown by this much.
      rotation_weight_mm: metres of translation one radian of rotation counts as in OMPL's SE(3)
        distance; the jaw length, so that a distance bounds the motion of any jaw point.
      check_step_mm: the state spacing OMPL uses where a planner cuts a motion into states itself
        (largest motion of any tool point between two); motions are validated whole.
      rrt_range_mm: RRT*'s and RRT-Connect's longest extension (OMPL's "range"), in the weighted
        SE(3) distance.
      checker: ``mujoco`` (:class:`~regrasp_mjx.envs.host.HostChecker`: CPU MuJoCo's collision of the
        counted capsule pairs, a Python call per checked state) or ``lean``
        (:class:`~regrasp_mjx.envs.lean_checker.LeanChecker`: the same pairs and verdicts from the
        lean planner's compiled test, a whole motion's states in one call). Same verdicts (tested),
        so the same plans for the same seed; ``lean`` is faster.
    """

    planner: str = "BITstar"
    direction: str = "reverse"
    budget_s: float = 10.0
    simplify_s: float = 0.2
    margin_mm: float = 8.0
    rotation_weight_mm: float = 10.2
    check_step_mm: float = 0.25
    rrt_range_mm: float = 2.0
    checker: str = "mujoco"

    def __post_init__(self) -> None:
        require(self.planner in PLANNERS, "planner", self.planner, f"one of {PLANNERS}")
        require(self.direction in DIRECTIONS, "direction", self.direction, f"one of {DIRECTIONS}")
        require(self.checker in CHECKERS, "checker", self.checker, f"one of {CHECKERS}")
        names = ("budget_s", "margin_mm", "rotation_weight_mm", "check_step_mm", "rrt_range_mm")
        require_numbers(self, names, lambda v: v > 0, "a finite number > 0")
        require_numbers(self, ("simplify_s",), lambda v: v >= 0, "a finite number >= 0")


@dataclasses.dataclass
class PlanResult:
    """A planning outcome. ``poses`` is (K, 7) ``[x, y, z, qw, qx, qy, qz]`` from start to goal."""

    solved: bool
    plan_time_s: float
    poses: np.ndarray | None = None
    path_length_mm: float = float("nan")
    error: str = ""


def _import_ompl():
    # imported where a planner is built: OMPL's C++ libraries load only in the planner processes
    from ompl import base as ob, geometric as og, util as ou  # noqa: I001

    return ob, og, ou


def _set_state(state: Any, pose: np.ndarray) -> None:
    state.setXYZ(float(pose[0]), float(pose[1]), float(pose[2]))
    rot = state.rotation()
    rot.w, rot.x, rot.y, rot.z = (float(v) for v in pose[3:7])


def _get_pose(state: Any) -> np.ndarray:
    rot = state.rotation()
    return np.array([state.getX(), state.getY(), state.getZ(), rot.w, rot.x, rot.y, rot.z])


def _unit_pose(name: str, pose: np.ndarray) -> np.ndarray:
    pose = np.array(pose, np.float64).reshape(-1)
    if pose.shape != (7,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} pose must be 7 finite numbers [x, y, z, qw, qx, qy, qz], got {pose}")
    pose[3:] = unit_quaternions(f"{name} pose", pose[3:])
    return pose


def translation_length_mm(poses: np.ndarray) -> float:
    """Sum of the translations along a path, mm (the paper's path length)."""
    return float(np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1).sum() * 1e3)


class OmplPlanner:
    """Plans one problem at a time; owns its collision checker (``config.checker``'s kind: a given
    :class:`HostChecker` is turned into a :class:`LeanChecker` of its scene and margin for
    ``checker="lean"``). Not thread-safe."""

    def __init__(
        self, config: PlannerConfig = PlannerConfig(), checker: HostChecker | LeanChecker | None = None, seed: int = 0
    ):
        self.config = config
        checker = checker if checker is not None else HostChecker()
        if config.checker == "lean" and not isinstance(checker, LeanChecker):
            checker = LeanChecker(checker.scene, checker.clearance_mm)
        self.checker = checker
        self.ob, self.og, self.ou = _import_ompl()
        self.ou.RNG.setSeed(int(seed) % (2**31 - 1) + 1)  # before any space or planner is built
        self.ou.setLogLevel(self.ou.LogLevel.LOG_ERROR)

    def plan(self, needle: np.ndarray, start: np.ndarray, goal: np.ndarray) -> PlanResult:
        """Plans from ``start`` to ``goal`` (7-vectors, e_g frame) around ``needle`` (7-vector).

        Returns a :class:`PlanResult`; ``poses`` always run from start to goal, whatever the
        direction the planner searched in.
        """
        ob, og = self.ob, self.og
        cfg = self.config
        t0 = time.perf_counter()
        # float64 unit quaternions: OMPL's SE(3) distance takes acos of a dot product, which a
        # float32 quaternion (|q| = 1 +- 1e-7) pushes past 1 into NaN, and then no goal is reached.
        needle, start, goal = (
            _unit_pose(name, v) for name, v in (("needle", needle), ("start", start), ("goal", goal))
        )
        needle_pos, needle_quat = needle[:3], needle[3:]
        if self.checker.collides(needle_pos, needle_quat, start[:3], start[3:]):
            return PlanResult(False, time.perf_counter() - t0, error="start in collision")
        if self.checker.collides(needle_pos, needle_quat, goal[:3], goal[3:]):
            return PlanResult(False, time.perf_counter() - t0, error="goal in collision")

        space = ob.SE3StateSpace()
        bounds = ob.RealVectorBounds(3)
        lo = np.minimum(start[:3], goal[:3]) - cfg.margin_mm * 1e-3
        hi = np.maximum(start[:3], goal[:3]) + cfg.margin_mm * 1e-3
        for i in range(3):
            bounds.setLow(i, float(lo[i]))
            bounds.setHigh(i, float(hi[i]))
        space.setBounds(bounds)
        space.setSubspaceWeight(1, cfg.rotation_weight_mm * 1e-3)
        setup = og.SimpleSetup(space)
        si = setup.getSpaceInformation()
        checker = self.checker
        if isinstance(checker, LeanChecker):
            placed = checker.place(needle)

            def is_valid(state) -> bool:
                if not space.satisfiesBounds(state):
                    return False
                r = state.rotation()
                return not checker.pose_collides(placed, state.getX(), state.getY(), state.getZ(), r.w, r.x, r.y, r.z)

            motions = _lean_motions(ob, si, space, checker, placed)  # kept alive by this frame while planning
            si.setMotionValidator(motions)
        else:

            def is_valid(state) -> bool:
                if not space.satisfiesBounds(state):
                    return False
                p = _get_pose(state)
                return not checker.collides(needle_pos, needle_quat, p[:3], p[3:])

            motions = _host_motions(ob, si, space, checker, needle)  # kept alive by this frame while planning
            si.setMotionValidator(motions)

        setup.setStateValidityChecker(is_valid)
        # Motions are tested whole (the validators above); the resolution remains what OMPL's
        # planners use to cut motions into states of their own (a distance bounds how far any jaw
        # point moves, the rotation weighted by the jaw length).
        si.setStateValidityCheckingResolution(cfg.check_step_mm * 1e-3 / space.getMaximumExtent())
        a, b = (goal, start) if cfg.direction == "reverse" else (start, goal)
        s_a, s_b = space.allocState(), space.allocState()
        _set_state(s_a, a)
        _set_state(s_b, b)
        setup.setStartAndGoalStates(s_a, s_b)
        # Any path satisfies the objective, so the optimising planners return their first solution
        # (the paper's planning time is time to a solution, not time spent optimising).
        objective = ob.PathLengthOptimizationObjective(si)
        objective.setCostThreshold(ob.Cost(math.inf))
        setup.setOptimizationObjective(objective)
        planner = getattr(og, "BFMT" if cfg.planner == "BFMTstar" else cfg.planner)(si)
        if cfg.planner in ("RRTstar", "RRTConnect"):
            # OMPL's default range (a fifth of the space's extent, ~10 mm here) makes almost every
            # extension near the needle collide; a few millimetres lets the tree into the funnel.
            planner.setRange(cfg.rrt_range_mm * 1e-3)
        setup.setPlanner(planner)
        setup.setup()
        pdef = setup.getProblemDefinition()
        stop = ob.plannerOrTerminationCondition(
            ob.timedPlannerTerminationCondition(cfg.budget_s), ob.exactSolnPlannerTerminationCondition(pdef)
        )
        setup.solve(stop)
        if not setup.haveExactSolutionPath():
            return PlanResult(False, time.perf_counter() - t0, error="no exact solution within the budget")
        if cfg.simplify_s > 0:
            setup.simplifySolution(cfg.simplify_s)
        path = setup.getSolutionPath()
        poses = np.array([_get_pose(path.getState(i)) for i in range(path.getStateCount())])
        if cfg.direction == "reverse":
            poses = poses[::-1].copy()
        poses[:, 3:] *= np.sign(poses[:, 3:4] + 1e-300)  # w >= 0
        elapsed = time.perf_counter() - t0
        return PlanResult(True, elapsed, poses, translation_length_mm(poses))


def _lean_motions(ob: Any, si: Any, space: Any, checker: LeanChecker, placed: Held) -> Any:
    """An OMPL motion validator that tests the whole motion between two states (position linear,
    orientation slerped, as OMPL interpolates; :mod:`regrasp_mjx.world.continuous`) in one compiled call
    (:meth:`LeanChecker.motion_collides`)."""

    class LeanMotions(ob.MotionValidator):
        def checkMotion(self, s1: Any, s2: Any, *last_valid: Any) -> bool:
            if last_valid:  # the planners used here call the two-state form only
                raise NotImplementedError("checker='lean' checks two-state motions only (what the PLANNERS call)")
            if not space.satisfiesBounds(s2):  # the states between are inside the box when both ends are
                return False
            return not checker.motion_collides(placed, _get_pose(s1), _get_pose(s2))

    return LeanMotions(si)


def _host_motions(ob: Any, si: Any, space: Any, checker: HostChecker, needle: np.ndarray) -> Any:
    """An OMPL motion validator that tests the whole motion between two states (position linear,
    orientation slerped, as OMPL interpolates) with the host checker's continuous test."""

    class HostMotions(ob.MotionValidator):
        def checkMotion(self, s1: Any, s2: Any, *last_valid: Any) -> bool:
            if last_valid:  # the planners used here call the two-state form only
                raise NotImplementedError("the motion validator checks two-state motions only (what the PLANNERS call)")
            if not space.satisfiesBounds(s2):
                return False
            a, b = _get_pose(s1), _get_pose(s2)
            return not (
                checker.collides(needle[:3], needle[3:], b[:3], b[3:]) or checker.motion_collides_between(needle, a, b)
            )

    return HostMotions(si)


def straight_line(
    checker: HostChecker,
    needle: np.ndarray,
    start: np.ndarray,
    goal: np.ndarray,
    config: PlannerConfig = PlannerConfig(),
) -> PlanResult:
    """The straight-line baseline (SPEC): position interpolated, orientation slerped, the whole
    motion tested (:mod:`regrasp_mjx.world.continuous`)."""

    t0 = time.perf_counter()
    needle, start, goal = (_unit_pose(name, v) for name, v in (("needle", needle), ("start", start), ("goal", goal)))
    for name, pose in (("start", start), ("goal", goal)):
        if checker.collides(needle[:3], needle[3:], pose[:3], pose[3:]):
            return PlanResult(False, time.perf_counter() - t0, error=f"{name} in collision")
    if checker.motion_collides_between(needle, start, goal):
        return PlanResult(False, time.perf_counter() - t0, error="collision along the straight line")
    poses = np.stack([start, goal])
    return PlanResult(True, time.perf_counter() - t0, poses, translation_length_mm(poses))
