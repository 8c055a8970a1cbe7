"""``python -m regrasp_mjx.export_minari``: a demonstration set as a Minari dataset (the field's offline-RL format).

Each demonstration of ``--demos`` (what ``python -m regrasp_mjx.demos`` wrote) is replayed through
the gymnasium environment of its task, and the dataset named ``--name`` holds what that environment
returned, with its spaces and its spec: :mod:`regrasp_mjx.interfaces.minari_export` says how. It is
written under ``MINARI_DATASETS_PATH`` (Minari's default: ``~/.minari/datasets``), whole or not at all.
A command of its own rather than an option of ``demos``: an export reads a finished set, which
``demos`` would first resume (every plan file read and replayed again, its planner arguments repeated).
Needs the minari extra: ``pip install -e ".[minari]"``.
"""

from __future__ import annotations

import argparse
import sys

from regrasp_mjx.core.atomic import dumps
from regrasp_mjx.core.config import ConfigError
from regrasp_mjx.core.host_loop import run_command
from regrasp_mjx.interfaces.minari_export import ID_FORM, ExportError, export, name_problem
from regrasp_mjx.planning.episodes import DemosError


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m regrasp_mjx.export_minari", description=__doc__.splitlines()[0])
    p.add_argument(
        "--demos", required=True, help="a demonstration set (python -m regrasp_mjx.demos): its folder or its demos.npz"
    )
    p.add_argument("--name", required=True, help=f"the dataset's id: {ID_FORM}")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset of that id (default: refuse)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if problem := name_problem(args.name, args.overwrite):  # before any work
        p.error(problem)
    try:
        summary = export(args.demos, args.name, overwrite=args.overwrite, quiet=args.quiet)
    except (ExportError, DemosError, ConfigError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main, "nothing was written: run the same command again"))
