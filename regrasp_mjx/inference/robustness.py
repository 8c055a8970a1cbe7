"""How a policy copes with a wrong needle estimate: frame noise, a fixed bias, a clearance margin.

A lab never has the exact needle pose (the paper's real robot fell from 97 % to 73 % on exactly
this). :func:`measure` runs a policy on test-set problems with each step's needle estimate drawn
from :class:`~regrasp_mjx.envs.estimates.NeedleNoise` and judges success and collisions on the true
needle, in one of three modes (:data:`MODES`):

- ``open``: one camera frame, one plan, executed open loop (what the paper's real-robot runs did);
  at no noise this is ``Policy.plan`` exactly;
- ``per-frame``: closed loop, each step acting on that step's frame alone, stopping when that frame
  says the goal is reached (``per-frame-stop``: when it says the pose is within the policy's own
  stop tolerance, ``Policy.closed_loop_defaults``);
- ``fused``: closed loop on the mean of the frames so far, with the policy's own warm-up frames and
  stop tolerance (``Policy.execute``'s defaults; 10 frames and 0.7 for a policy that names none).

A clearance margin ``clearance_mm`` judges (and shields) every pose with that much kept from the
needle and the other tool. :data:`CONDITIONS` are the rows of the robustness table
(:func:`table`): ``python -m regrasp_mjx.evaluate --robustness`` prints it for one policy,
``python -m regrasp_mjx.compare --robustness`` for several (every shipped one by default).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from regrasp_mjx.core.config import ConfigError, is_number, require
from regrasp_mjx.envs.env import RegraspEnv
from regrasp_mjx.envs.estimates import NeedleNoise
from regrasp_mjx.inference.policy_file import resolve
from regrasp_mjx.robot.robot_errors import OBSERVE, RobotErrors, check_observe
from regrasp_mjx.world.sampling import episode_needles, episode_poses

# mode -> Policy.execute's keywords
MODES: dict[str, dict[str, Any]] = {
    "open": {"frames": "one", "warmup_frames": 1, "stop_tolerance": 1.0},
    "per-frame": {"frames": "each", "warmup_frames": 1, "stop_tolerance": 1.0},
    "per-frame-stop": {"frames": "each", "warmup_frames": 1},
    "fused": {"frames": "fused"},
}
MAX_NOISE_MM = 10.0  # NeedleNoise's range
MAX_CLEARANCE_MM = 1.0  # EnvConfig's range


@dataclasses.dataclass(frozen=True)
class Condition:
    """One row of the robustness table: frame noise ``sigma_mm``, a fixed bias ``bias_mm`` and a
    clearance margin ``clearance_mm`` (each checked: finite, within its range); the robot's errors
    ``robot`` (:class:`~regrasp_mjx.robot.robot_errors.RobotErrors`) and how the policy sees its tools,
    ``observe``; ``modes``: the only modes it is measured in (None: every one asked)."""

    name: str
    sigma_mm: float = 0.0
    bias_mm: float = 0.0
    clearance_mm: float = 0.0
    robot: RobotErrors = RobotErrors()
    observe: str = "camera"
    modes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        check_condition(self.sigma_mm, self.bias_mm, self.clearance_mm)
        check_observe(self.observe)
        if not isinstance(self.robot, RobotErrors):
            raise ConfigError(f"robot={self.robot!r} is not accepted: a RobotErrors")


def check_condition(sigma_mm: float, bias_mm: float, clearance_mm: float) -> None:
    """Raises :class:`ConfigError` naming the bad value and what is accepted."""
    for name, v, hi in (
        ("noise_mm", sigma_mm, MAX_NOISE_MM),
        ("bias_mm", bias_mm, MAX_NOISE_MM),
        ("clearance_mm", clearance_mm, MAX_CLEARANCE_MM),
    ):
        require(is_number(v) and 0.0 <= v <= hi, name, v, f"a finite number of millimetres in [0, {hi:g}]")


CONDITIONS = (
    Condition("exact"),
    Condition("sigma 0.1 mm", 0.1),
    Condition("sigma 0.25 mm", 0.25),
    Condition("sigma 0.5 mm", 0.5),
    Condition("bias 0.25 mm + sigma 0.25 mm", 0.25, 0.25),
    Condition("margin 0.1 mm", clearance_mm=0.1),
    Condition("margin 0.2 mm", clearance_mm=0.2),
)
# the robot's errors (issue 45): camera-to-base calibration T mm / R deg of each arm, joint offsets up to
# 0.5 (deg, mm), needle and tool tracking noise 0.25 mm; fused closed loop, each way of seeing the tools
CALIBRATIONS = ((0.0, 0.0), (1.0, 1.0), (3.0, 2.0), (5.0, 3.0), (10.0, 5.0))
ROBOT_CONDITIONS = tuple(
    Condition(
        f"calibration {t:g} mm {r:g} deg ({observe})" if t else f"tools tracked ({observe})",
        0.25,
        robot=RobotErrors(t, r, 0.5 if t else 0.0, 0.25),
        observe=observe,
        modes=("fused",),
    )
    for t, r in CALIBRATIONS
    for observe in OBSERVE
)


def program_groups(modes: tuple[str, ...], names: tuple[str, ...] | None = None) -> list[tuple[str, list[str]]]:
    """The rows of a table (``modes`` x the conditions named ``names``, all where None) grouped by
    the compiled program they run: ``[(mode, [condition names])]``, in table order. A group
    compiles one program (a mode, a clearance margin, a way of seeing the tools, joints or not;
    the noise is the program's argument), so groups run side by side compile side by side
    (``python -m regrasp_mjx.recipe``'s report; join their files with ``compare --merge``)."""
    groups: dict[tuple, tuple[str, list[str]]] = {}
    for mode in modes:
        for c in CONDITIONS + ROBOT_CONDITIONS:
            if (names is not None and c.name not in names) or (c.modes is not None and mode not in c.modes):
                continue
            key = (mode, c.clearance_mm, c.observe, c.robot.joint_offset > 0)
            groups.setdefault(key, (mode, []))[1].append(c.name)
    return list(groups.values())


def measure(
    policy, episodes, condition: Condition, mode: str = "fused", seed: int = 0, shield: bool = True
) -> dict[str, Any]:
    """Rates of one pass over test-set rows ``episodes`` under ``condition`` in ``mode``, judged on
    the true needle: ``success_rate``, ``collision_rate``, ``time_out_rate``, ``wrong_stop_rate``
    (stopped where the estimate, not the truth, was at the goal) and the mean ``steps`` of the
    successes, over the ``problems_valid`` problems whose start and goal keep the condition's
    clearance margin (all of a test set at no margin: with one, a start already within it fails
    before any step, whatever the policy; ``success_rate_all`` counts those as failures)."""
    if mode not in MODES:
        raise ConfigError(f"mode={mode!r} is not accepted: one of {tuple(MODES)}")
    if condition.clearance_mm != policy.env_config.clearance_mm:
        policy = policy.with_env(clearance_mm=condition.clearance_mm)
    needle, start, goal = episode_poses(episodes)
    r = policy.execute(
        needle,
        start,
        goal,
        NeedleNoise(condition.sigma_mm, condition.bias_mm),
        shield=shield,
        seed=seed,
        robot=condition.robot,
        observe=condition.observe,
        **MODES[mode],
        **episode_needles(episodes),
    )
    valid = clear_problems(policy.env_config, episodes)
    ok, collided = r["success"][valid], (r["collision"] | ~r["start_valid"])[valid]
    return {
        "condition": condition.name,
        "mode": mode,
        "sigma_mm": condition.sigma_mm,
        "bias_mm": condition.bias_mm,
        "clearance_mm": condition.clearance_mm,
        **dataclasses.asdict(condition.robot),
        "observe": condition.observe,
        "shield": shield,
        "seed": seed,
        "problems": int(valid.size),
        "problems_valid": int(valid.sum()),
        "success_rate": float(ok.mean()),
        "success_rate_all": float(r["success"].mean()),
        "collision_rate": float(collided.mean()),
        "time_out_rate": float(r["time_out"][valid].mean()),
        "wrong_stop_rate": float((r["stopped"][valid] & ~ok & ~collided).mean()),
        "steps": float(r["steps"][valid][ok].mean()) if ok.any() else None,
    }


def clear_problems(env_config, episodes) -> np.ndarray:
    """``[N]`` whether each problem's start and goal keep ``env_config.clearance_mm`` from the
    needle and the other tool (its own needle where the task varies needles), by the collision
    model the environment judges with."""
    rows = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), episodes)
    return np.asarray(_clear_program(env_config)(rows))


@functools.lru_cache(maxsize=8)
def _clear_program(env_config):
    """One compiled check per environment configuration (a table asks 28 times for a few)."""
    env = RegraspEnv(env_config)

    def clear(e):
        start = jnp.min(env.needle_distances(e, e.start_pos, e.start_quat))
        goal = jnp.min(env.needle_distances(e, e.goal_pos, e.goal_quat))
        return jnp.minimum(start, goal) > env.clearance

    return jax.jit(jax.vmap(clear))


def table(
    policy, episodes, modes: tuple[str, ...] = tuple(MODES), seed: int = 0, conditions=CONDITIONS, log=None
) -> list[dict[str, Any]]:
    """:func:`measure` for every condition and mode (shielded); one row each."""
    rows = []
    for condition in conditions:
        for mode in modes:
            if condition.modes is not None and mode not in condition.modes:
                continue
            rows.append(measure(policy, episodes, condition, mode, seed))
            if log is not None:
                r = rows[-1]
                log(
                    f"  {condition.name:<30} {mode:<9} success {r['success_rate']:.3f}  collision {r['collision_rate']:.3f}"
                )
    return rows


def markdown(rows: list[dict[str, Any]], modes: tuple[str, ...] | None = None) -> list[str]:
    """The rows of one policy as a table: conditions down, modes across (success, and collisions
    where there are any); ``modes`` None: those the rows hold, in :data:`MODES` order."""
    modes = modes or tuple(m for m in MODES if any(r["mode"] == m for r in rows))
    lines = ["| condition | " + " | ".join(modes) + " |", "| --- |" + " ---: |" * len(modes)]
    for name in dict.fromkeys(r["condition"] for r in rows):
        cells = []
        for mode in modes:
            r = next((r for r in rows if r["condition"] == name and r["mode"] == mode), None)
            if r is None:
                cells.append("–")
                continue
            coll = f" (coll. {r['collision_rate']:.3f})" if r["collision_rate"] > 0 else ""
            valid = f" [{r['problems_valid']}/{r['problems']}]" if r["problems_valid"] < r["problems"] else ""
            cells.append(f"{r['success_rate']:.3f}{coll}{valid}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def title(table: dict[str, Any], machine: bool = False) -> list[str]:
    """The line above one policy's table: its name, folder, network, hash and problems."""
    where = f"; {table['machine']}" if machine else ""
    net = "x".join(map(str, table["hidden"]))
    return [
        f"**{table['policy']}** (`{table['folder']}`, {net}, hash {table['policy_hash']}) on {table['problems']}{where}:",
        "",
    ]


def merge(parts: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One list of tables from the table files of several runs (``python -m regrasp_mjx.compare
    --robustness``, e.g. parts run side by side on one GPU): the parts of one policy (its noise rows
    and its margin rows run apart) become one table, rows in :data:`CONDITIONS` order. Raises when
    two parts of one policy name measured another policy file or other problems."""
    by_policy: dict[str, dict[str, Any]] = {}
    for data in parts:
        for t in data["tables"]:
            if "machine" not in t:  # a part made before the tables named their machine
                t = {**t, "machine": f"{data['backend']} ({data['device']})", "seed": data["seed"]}
            seen = by_policy.get(t["policy"])
            if seen is None:
                by_policy[t["policy"]] = {**t, "rows": list(t["rows"])}
                continue
            if (seen["policy_hash"], seen["problems"]) != (t["policy_hash"], t["problems"]):
                raise ConfigError(f"{t['policy']} was measured with another policy file or problems in another part")
            seen["rows"] += t["rows"]
            seen["wall_s"] = seen.get("wall_s", 0.0) + t.get("wall_s", 0.0)
            if t["machine"] not in seen["machine"]:
                seen["machine"] += f"; {t['machine']}"
    order = {c.name: i for i, c in enumerate(CONDITIONS + ROBOT_CONDITIONS)}
    for t in by_policy.values():
        t["rows"].sort(key=lambda r: order.get(r["condition"], len(order)))
    return list(by_policy.values())


NOISE_NAMES = frozenset(c.name for c in CONDITIONS)
ROBOT_NAMES = frozenset(c.name for c in ROBOT_CONDITIONS)

# The docs' summary: these policies side by side (docs/results.md), their full tables in
# experiments/RESULTS.md; each between `<!-- robustness:begin KIND -->` and `<!-- robustness:end -->`,
# written by `python experiments/robustness.py --docs` from robustness.json (a test compares them).
DOC_POLICIES = ("default", "exact")
DOC_MODES = ("open", "per-frame", "per-frame-stop", "fused")
ROBOT_DOC_POLICIES = ("default", "general")  # the docs' robot-error summary: the specialist and the generalist


def docs_blocks(tables: list[dict[str, Any]], policies: tuple[str, ...] = DOC_POLICIES) -> dict[str, list[str]]:
    """The docs' generated blocks from the tables of ``python -m regrasp_mjx.compare --robustness`` (its JSON's
    ``tables``): ``"summary"``, the policies side by side (open / per-frame (its own stop) / fused),
    and ``"tables"``, each policy's full table; both name the policy hashes they measured."""
    by_name = {t["policy"]: t for t in tables}
    missing = [p for p in policies if p not in by_name]
    if missing:
        raise ConfigError(f"the robustness tables hold no policy named {missing}; accepted: {sorted(by_name)}")
    chosen = [by_name[p] for p in policies]
    named = ", ".join(f"{t['policy']} hash {t['policy_hash']}" for t in chosen)
    machines = sorted({t.get("machine", "?") for t in chosen})
    source = (
        f"Measured: {named}; {chosen[0]['problems']}; shielded; {', '.join(machines)}; seed {chosen[0].get('seed', 0)}."
    )

    def cell(t, condition, mode):
        return next(r for r in t["rows"] if r["condition"] == condition and r["mode"] == mode)

    summary = [
        source,
        "",
        "| condition | " + " | ".join(f"`{p}`: open / per frame (own stop) / fused" for p in policies) + " |",
    ]
    summary.append("| --- |" + " --- |" * len(policies))
    for condition in dict.fromkeys(r["condition"] for r in chosen[0]["rows"] if r["condition"] in NOISE_NAMES):
        cells = []
        for t in chosen:
            o, f1, fs, fu = (cell(t, condition, m) for m in DOC_MODES)
            cells.append(
                f"{o['success_rate']:.3f} / {f1['success_rate']:.3f} ({fs['success_rate']:.3f}) / {fu['success_rate']:.3f}"
            )
        first = cell(chosen[0], condition, "open")
        note = f" [{first['problems_valid']} valid]" if first["problems_valid"] < first["problems"] else ""
        summary.append(f"| {condition}{note} | " + " | ".join(cells) + " |")
    full = [source, ""]
    for t in chosen:
        full += [f"**{t['policy']}** (hash {t['policy_hash']}); success (collision rate) [valid problems]:", ""]
        full += markdown(t["rows"], tuple(m for m in DOC_MODES if any(r["mode"] == m for r in t["rows"]))) + [""]
    return {
        "summary": summary,
        "tables": full[:-1],
        "robot": robot_block(tables),
        "robot_summary": robot_block([by_name[p] for p in ROBOT_DOC_POLICIES if p in by_name]),
    }


def robot_block(tables: list[dict[str, Any]]) -> list[str]:
    """The robot-error rows (:data:`ROBOT_CONDITIONS`, fused closed loop) of the policies of
    ``tables`` that have them: calibration down, policies across, each cell ``kinematic / camera``
    success."""
    measured = [t for t in tables if any(r["condition"] in ROBOT_NAMES for r in t["rows"])]
    if not measured:
        return ["No policy's table holds the robot-error rows yet."]
    named = ", ".join(f"`{t['policy']}` {t['policy_hash']}" for t in measured)
    machines = sorted({t.get("machine", "?").split("; ")[-1] for t in measured})
    lines = [
        f"Measured: {named}; {' or '.join(dict.fromkeys(t['problems'] for t in measured))} (each policy its own "
        f"test set); fused closed loop, shielded; needle and tool tracking noise "
        f"0.25 mm, joint offsets up to 0.5 deg (mm) with a calibration error; {', '.join(machines)}; "
        f"seed {measured[0].get('seed', 0)}. Each cell: success with the tools seen through their kinematics / by the camera.",
        "",
        "| calibration error of each arm | " + " | ".join(f"`{t['policy']}`" for t in measured) + " |",
        "| --- |" + " ---: |" * len(measured),
    ]
    for t_mm, r_deg in CALIBRATIONS:
        label = f"{t_mm:g} mm, {r_deg:g} deg" if t_mm else "none (tools tracked)"
        cells = []
        for t in measured:
            got = []
            for observe in OBSERVE:
                name = f"calibration {t_mm:g} mm {r_deg:g} deg ({observe})" if t_mm else f"tools tracked ({observe})"
                r = next((r for r in t["rows"] if r["condition"] == name and r["mode"] == "fused"), None)
                got.append("–" if r is None else f"{r['success_rate']:.3f}")
            cells.append(" / ".join(got))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def replace_block(text: str, kind: str, lines: list[str]) -> str:
    """``text`` with the lines between ``<!-- robustness:begin KIND -->`` and the next
    ``<!-- robustness:end -->`` replaced by ``lines`` (raises when the markers are missing)."""
    begin, end = f"<!-- robustness:begin {kind} -->", "<!-- robustness:end -->"
    i = text.find(begin)
    j = text.find(end, i)
    if i < 0 or j < 0:
        raise ValueError(f"no {begin} ... {end} block")
    return text[: i + len(begin)] + "\n" + "\n".join(lines) + "\n" + text[j:]


def policy_hash(path: str | os.PathLike | None = None) -> str:
    """SHA-256 (first 16 hex digits) of a policy's ``policy.npz`` and ``policy.json``: what a
    table records so that a test can tell when the policy it measured has changed."""
    folder = resolve(path)
    h = hashlib.sha256()
    for name in ("policy.npz", "policy.json"):
        h.update(Path(folder, name).read_bytes())
    return h.hexdigest()[:16]
