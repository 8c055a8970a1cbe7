"""Configs from what a user types or a file holds: ``--set KEY=VALUE`` text, dotted field names
(``scene.jaw_angle_deg``) for nested configs, and the JSON dict a run saved its ``EnvConfig`` as.

The configs and their checks are :mod:`regrasp_mjx.core.config`; this module only builds them.
"""

from __future__ import annotations

import ast
import dataclasses
from typing import Any

from regrasp_mjx.core.config import ConfigError, EnvConfig, SceneConfig, TaskConfig


def replace(config: Any, **changes: Any) -> Any:
    """``dataclasses.replace`` that accepts dotted names for nested configs: ``scene.jaw_angle_deg``."""
    nested: dict[str, dict[str, Any]] = {}
    flat: dict[str, Any] = {}
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if not any(f.name == head for f in dataclasses.fields(config)):
            names = ", ".join(f.name for f in dataclasses.fields(config))
            raise ConfigError(f"{type(config).__name__} has no field {head!r}; fields: {names}")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            flat[head] = value
    for head, sub in nested.items():
        flat[head] = replace(getattr(config, head), **sub)
    return dataclasses.replace(config, **flat)


def env_config_from_dict(d: dict[str, Any]) -> EnvConfig:
    """The inverse of ``dataclasses.asdict(EnvConfig)`` (JSON lists back to tuples)."""
    try:
        task = {k: tuple(v) if isinstance(v, list) else v for k, v in d["task"].items()}
        rest = {k: v for k, v in d.items() if k not in ("scene", "task")}
        if "collision_substeps" in rest:  # files from before the continuous test (issue 44)
            if rest.pop("collision_substeps") is not None:
                raise ConfigError(
                    "collision_substeps is no longer accepted (every step is tested along its whole "
                    "motion, regrasp_mjx.world.continuous); accepted: null or absent"
                )
        return EnvConfig(scene=SceneConfig(**d["scene"]), task=TaskConfig(**task), **rest)
    except (KeyError, TypeError) as err:
        raise ConfigError(f"not an EnvConfig description: {err}") from err


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` items as ``{KEY: value}``, values read as Python literals where they parse
    (``3``, ``0.2``, ``(256, 256)``, ``False``) and as strings otherwise; for :func:`replace`."""

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r} is not accepted: KEY=VALUE, e.g. --set env.horizon=80")
        try:
            out[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            out[key.strip()] = value.strip()
    return out
