"""The XLA flags the package adds when imported: added once, never over the user's own, and not at all
when opted out."""

from __future__ import annotations

import os

import regrasp_mjx  # noqa: F401  (its import applies the flags)
from regrasp_mjx.core import xla_flags


def test_xla_flags_are_added_unless_the_user_set_them_or_opted_out():
    # the package's import added them to this process (conftest imports it before JAX starts)
    assert (
        all(flag in os.environ.get("XLA_FLAGS", "") for flag in xla_flags.FLAGS)
        or os.environ.get(xla_flags.OPT_OUT) == "0"
    )
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert xla_flags.apply(env).split() == ["--xla_force_host_platform_device_count=2", *xla_flags.FLAGS]
    assert xla_flags.apply(env) == env["XLA_FLAGS"]  # twice: nothing added again
    mine = {"XLA_FLAGS": "--xla_gpu_enable_command_buffer="}  # the user's own value of one of them wins
    assert xla_flags.apply(mine).split() == ["--xla_gpu_enable_command_buffer=", xla_flags.FLAGS[1]]
    empty: dict[str, str] = {}
    assert xla_flags.apply(empty) == " ".join(xla_flags.FLAGS)
    out = {xla_flags.OPT_OUT: "0"}
    assert xla_flags.apply(out) == "" and "XLA_FLAGS" not in out
