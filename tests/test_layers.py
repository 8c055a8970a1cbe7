"""The package's layers as docs/architecture.md draws them: no module imports from a layer above its
own, the command lines are the top layer and no module imports one, no import cycles (imports inside functions counted), and few imports inside functions, each
saying why (an optional dependency or start-up time)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "regrasp_mjx"
MAX_LOCAL_IMPORTS = 11


def modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = path
    return out


def table() -> list[tuple[float, str, int, list[str]]]:
    """docs/architecture.md's rows: ``(layer, module prefix, module count, modules)``; ``4b`` is 4.5
    (beside 4a, above it), ``5a``/``5b`` 5.0/5.5; a folder's prefix is ``regrasp_mjx.<folder>.``, the
    package root's ``regrasp_mjx.``."""
    rows = []
    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        m = re.match(r"\| (\d)([ab]?)\. [^|]+\| ([^|]+)\| ([^|]+)\|", line)
        if not m:
            continue
        level = int(m.group(1)) + (0.5 if m.group(2) == "b" else 0.0)
        where = re.fullmatch(r"\s*(?:`(\w+)/`|the package root) \((\d+)\)\s*", m.group(3))
        assert where, f"docs/architecture.md: a layer's folder cell reads {m.group(3)!r}"
        prefix = f"regrasp_mjx.{where.group(1)}." if where.group(1) else "regrasp_mjx."
        names = []
        for name in re.findall(r"`([^`]+)`", m.group(4)):
            if ".{" in name:  # ddpg_bc.{config, networks}
                base, rest = name.split(".{")
                names += [f"{base}.{x}" for x in rest.rstrip("}").split(", ")]
            else:
                names.append(name)
        rows.append((level, prefix, int(where.group(2)), names))
    return rows


def layers() -> dict[str, float]:
    """Module -> layer from the table in docs/architecture.md."""
    return {prefix + name: level for level, prefix, _, names in table() for name in names}


def imports(mods: dict[str, Path]) -> tuple[dict[str, set[str]], list[tuple[str, int, str]]]:
    """Each module's imports of package modules (anywhere in it) and the imports inside functions
    ``(module, line, source line)``."""
    graph: dict[str, set[str]] = {name: set() for name in mods}
    local = []
    for name, path in mods.items():
        text = path.read_text()
        tree = ast.parse(text)
        in_function = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                in_function |= {id(n) for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))}
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            if id(node) in in_function:
                local.append((name, node.lineno, text.splitlines()[node.lineno - 1]))
            if isinstance(node, ast.ImportFrom):
                if not (node.module or "").startswith("regrasp_mjx"):
                    continue
                subs = {f"{node.module}.{a.name}" for a in node.names} & set(mods)
                targets = subs or {node.module}
            else:
                targets = {a.name for a in node.names if a.name.startswith("regrasp_mjx")}
            graph[name] |= {t for t in targets if t in mods and t != name}
    return graph, local


def test_every_module_has_a_layer_and_imports_only_from_its_own_or_lower_ones():
    mods, level = modules(), layers()
    packages = {name for name, path in mods.items() if path.name == "__init__.py"}
    assert sorted(set(mods) - set(level) - packages) == [], "modules missing from docs/architecture.md's table"
    assert sorted(set(level) - set(mods)) == [], "docs/architecture.md names modules that do not exist"
    graph, _ = imports(mods)
    up = [(a, level[a], b, level[b]) for a in level for b in graph[a] if b in level and level[b] > level[a]]
    assert up == [], f"imports from a higher layer: {up}"


def test_the_commands_are_the_top_layer_and_no_module_imports_one():
    """The command-line modules (the package root's row) only parse arguments, call and print: they sit
    alone above every other layer, and what another module needs (a library module or another command)
    lives in a layer below, so no module imports a command, not even inside a function."""
    rows = table()
    top = next(level for level, prefix, _, _ in rows if prefix == "regrasp_mjx.")
    below = [(level, prefix) for level, prefix, _, _ in rows if prefix != "regrasp_mjx."]
    assert all(level < top for level, _ in below), f"a layer at or above the commands' ({top}): {below}"
    commands = {name for name, level in layers().items() if level == top}
    graph, _ = imports(modules())
    into = sorted((a, b) for a in graph for b in graph[a] if b in commands)
    assert into == [], f"modules importing a command module: {into}"


def test_no_import_cycles_counting_imports_inside_functions():
    graph, _ = imports(modules())
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(name, path):
        state[name] = 1
        for nxt in sorted(graph[name]):
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(nxt) :] + [nxt]))
            if nxt not in state:
                visit(nxt, path + [nxt])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])


def test_imports_inside_functions_are_few_and_each_says_why():
    mods = modules()
    _, local = imports(mods)
    assert len(local) <= MAX_LOCAL_IMPORTS, [f"{m}:{n}" for m, n, _ in local]
    for name, line, source in local:
        above = mods[name].read_text().splitlines()[line - 2]
        assert "#" in source or "#" in above, f"{name}:{line} imports inside a function without saying why"


def test_no_module_is_over_400_lines():
    """Small modules whose names say what they hold (issue 50): split one that grows past 400 lines."""
    long = {name: n for name, path in modules().items() if (n := len(path.read_text().splitlines())) > 400}
    assert not long, f"modules over 400 lines: {long}"


def test_the_folders_are_the_layers():
    """Each row of the table is one folder (or the package root) and counts its modules; the package
    root holds only the command-line modules, ``__init__`` and the layer folders (plus package data)."""
    mods = modules()
    for _, prefix, count, names in table():
        assert count == len(names), f"{prefix}: the table counts {count} modules and lists {len(names)}"
        if prefix != "regrasp_mjx.":
            folder = prefix.rstrip(".")
            inside = {m for m in mods if m.startswith(prefix) and mods[m].name != "__init__.py"}
            assert inside == {prefix + n for n in names}, f"{folder}: the table and the folder differ"
            assert (PACKAGE / folder.split(".", 1)[1] / "__init__.py").read_text().startswith('"""Layer')
    root = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__"}
    commands = next(names for _, prefix, _, names in table() if prefix == "regrasp_mjx.")
    assert root == {n for n in commands if "." not in n}, "the package root holds a module that is not a command"
    data = {"data", "models", "policies", "__pycache__"}
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir()} - data
    assert folders == {prefix.split(".")[1] for _, prefix, _, _ in table() if prefix != "regrasp_mjx."}
