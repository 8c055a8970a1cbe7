"""A command's ``main`` run in-process, its exit code and what it printed (for the CLI tests)."""

from __future__ import annotations

import contextlib
import io


def run_main(main, argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as stop:
            code = stop.code
    return code, out.getvalue(), err.getvalue()
