"""The robustness tables as text: one policy's rows as markdown, the tables of runs made apart
merged into one per policy, and the docs' generated blocks (``python experiments/robustness.py
--docs``), each naming the policy hashes it measured. The measuring is
:mod:`regrasp_mjx.inference.robustness`'s."""

from __future__ import annotations

from typing import Any

from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.inference.robustness import (
    CALIBRATIONS,
    CAMERA_CONDITIONS,
    CONDITIONS,
    FITTED_CONDITIONS,
    MODES,
    NAMED_CONDITIONS,
    ROBOT_CONDITIONS,
    robot_condition_name,
)
from regrasp_mjx.robot.robot_errors import OBSERVE


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
        f"**{table['policy']}** (`{table['folder']}`, {net}, hash {table['policy_hash']}) "
        f"on {table['problems']}{where}:",
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
    order = {c.name: i for i, c in enumerate(NAMED_CONDITIONS)}
    for t in by_policy.values():
        t["rows"].sort(key=lambda r: order.get(r["condition"], len(order)))
    return list(by_policy.values())


NOISE_NAMES = frozenset(c.name for c in CONDITIONS)
ROBOT_NAMES = frozenset(c.name for c in ROBOT_CONDITIONS)
CAMERA_NAMES = frozenset(c.name for c in CAMERA_CONDITIONS + FITTED_CONDITIONS)

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
                f"{o['success_rate']:.3f} / {f1['success_rate']:.3f} ({fs['success_rate']:.3f}) / "
                f"{fu['success_rate']:.3f}"
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


def camera_blocks(tables: list[dict[str, Any]]) -> dict[str, list[str]]:
    """The docs' blocks of a real camera's rows (their own table file, ``camera.json``):
    ``"camera"``, every policy that has them, and ``"camera_summary"``, the docs' two."""
    by_name = {t["policy"]: t for t in tables}
    return {
        "camera": camera_block(tables),
        "camera_summary": camera_block([by_name[p] for p in ROBOT_DOC_POLICIES if p in by_name]),
    }


def _measured(tables: list[dict[str, Any]], names: frozenset[str]) -> tuple[list, str, str, str, int]:
    """The tables that hold rows of ``names`` and what a block's first line says of them: the
    policies and hashes, their problem sets, the machines (each table's last) and the seed."""
    measured = [t for t in tables if any(r["condition"] in names for r in t["rows"])]
    named = ", ".join(f"`{t['policy']}` {t['policy_hash']}" for t in measured)
    problems = " or ".join(dict.fromkeys(t["problems"] for t in measured))
    machines = ", ".join(sorted({t.get("machine", "?").split("; ")[-1] for t in measured}))
    return measured, named, problems, machines, measured[0].get("seed", 0) if measured else 0


def robot_block(tables: list[dict[str, Any]]) -> list[str]:
    """The robot-error rows (:data:`ROBOT_CONDITIONS`, fused closed loop) of the policies of
    ``tables`` that have them: calibration down, policies across, each cell ``kinematic / camera``
    success."""
    measured, named, problems, machines, seed = _measured(tables, ROBOT_NAMES)
    if not measured:
        return ["No policy's table holds the robot-error rows yet."]
    lines = [
        f"Measured: {named}; {problems} (each policy its own "
        f"test set); fused closed loop, shielded; needle and tool tracking noise "
        f"0.25 mm, joint offsets up to 0.5 deg (mm) with a calibration error; {machines}; "
        f"seed {seed}. Each cell: success with the tools seen through their kinematics / by the camera.",
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
                name = robot_condition_name(t_mm, r_deg, observe)
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


def camera_block(tables: list[dict[str, Any]]) -> list[str]:
    """A real camera's rows (:data:`~regrasp_mjx.inference.robustness.CAMERA_CONDITIONS`, fused
    closed loop, each policy's own settings) of the policies of ``tables`` that have them: the
    camera's errors down, policies across, each cell ``success (collisions / wrong stops)``."""
    measured, named, problems, machines, seed = _measured(tables, CAMERA_NAMES)
    if not measured:
        return ["No policy's table holds a real camera's rows yet."]
    lines = [
        f"Measured: {named}; {problems} (each policy its own "
        "test set); fused closed loop at each policy's own settings, shielded; the tools and the needle seen by the "
        "camera, calibration 5 mm / 3 deg of each arm, joint offsets up to 0.5 deg (mm); "
        f"{machines}; seed {seed}. Each cell: success (collisions / stopped short "
        "of the true goal).",
        "",
        "| the camera's errors | " + " | ".join(f"`{t['policy']}`" for t in measured) + " |",
        "| --- |" + " ---: |" * len(measured),
    ]
    # a fitted preset's row only where a table holds it (it is asked for by name)
    fitted = [c for c in FITTED_CONDITIONS if any(r["condition"] == c.name for t in measured for r in t["rows"])]
    for condition in CAMERA_CONDITIONS + tuple(fitted):
        cells = []
        for t in measured:
            r = next((r for r in t["rows"] if r["condition"] == condition.name and r["mode"] == "fused"), None)
            cells.append(
                "–"
                if r is None
                else f"{r['success_rate']:.3f} ({r['collision_rate']:.3f} / {r['wrong_stop_rate']:.3f})"
            )
        lines.append(f"| {condition.name.removeprefix('camera: ')} | " + " | ".join(cells) + " |")
    return lines
