"""regrasp_mjx: learned rapid motion planning for bimanual suture-needle regrasping in MuJoCo MJX.

Public entry points: :func:`regrasp_mjx.load_policy` (the shipped policy with no path; its
``plan``, ``plan_from_camera``, ``closed_loop_step``, ``camera_loop`` and ``execute``),
:class:`regrasp_mjx.envs.env.RegraspEnv`, :func:`regrasp_mjx.core.geometry.grasp_pose`,
:func:`regrasp_mjx.world.scene.load_scene`, :func:`regrasp_mjx.world.sampling.load_testset`, and the CLIs
``python -m regrasp_mjx.{train,evaluate,compare,distill,sweep,demos,testset,grasps,export_onnx,export_minari}``
(the README's command table).
"""

import contextlib as _contextlib
import io as _io

from regrasp_mjx.core import xla_flags as _xla_flags

_xla_flags.apply()  # before anything starts JAX's backend: loops on the GPU run as CUDA graphs

import gymnasium as _gymnasium  # noqa: E402

# mujoco.mjx prints "Failed to import warp" (twice) to stdout when the optional NVIDIA Warp backend
# is absent, which we never use; importing it once here with stdout captured keeps every command's
# output (e.g. `evaluate --json`) to this project's own. Anything else it prints is passed on.
with _contextlib.redirect_stdout(_io.StringIO()) as _captured:
    import mujoco.mjx  # noqa: F401
for _line in _captured.getvalue().splitlines():
    if not _line.startswith(("Failed to import warp", "Failed to import mujoco_warp")):
        print(_line)

from regrasp_mjx.core.config import ConfigError, EnvConfig, SceneConfig, TaskConfig  # noqa: E402
from regrasp_mjx.core.geometry import grasp_pose  # noqa: E402

__version__ = "0.1.0"

# The gymnasium ids, one per environment of regrasp_mjx.interfaces.registry (tests/test_gym.py keeps the two
# lists equal): registered here with the modules as strings, so importing the package stays light.
GYM_NAMES = (
    "NeedleRegrasp",
    "NeedleRegraspGeneral",
    "NeedleRegraspNoisy",
    "NeedleRegraspCalibration",
    "NeedleRegraspCamera",
)


def _register_gymnasium() -> None:
    for name in GYM_NAMES:
        env_id = f"regrasp_mjx/{name}-v0"
        if env_id not in _gymnasium.registry:
            _gymnasium.register(
                id=env_id,
                entry_point="regrasp_mjx.interfaces.gym_envs:NeedleRegraspEnv",
                vector_entry_point="regrasp_mjx.interfaces.gym_envs:NeedleRegraspVectorEnv",
                kwargs={"name": name},
            )


_register_gymnasium()
__all__ = [
    "ConfigError",
    "EnvConfig",
    "SceneConfig",
    "TaskConfig",
    "grasp_pose",
    "load_policy",
    "Policy",
    "__version__",
]


def __getattr__(name: str):
    if name in ("load_policy", "Policy"):  # lazy: the policy module imports the learner's networks
        from regrasp_mjx.inference import policy

        return getattr(policy, name)
    raise AttributeError(f"module 'regrasp_mjx' has no attribute {name!r}")
