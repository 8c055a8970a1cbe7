"""regrasp_mjx: learned rapid motion planning for bimanual suture-needle regrasping in MuJoCo MJX.

Public entry points: :func:`regrasp_mjx.load_policy` (the shipped policy with no path),
:class:`regrasp_mjx.env.RegraspEnv`, :func:`regrasp_mjx.geometry.grasp_pose`,
:func:`regrasp_mjx.scene.load_scene`, :func:`regrasp_mjx.sampling.load_testset`, and the CLIs
``python -m regrasp_mjx.{train,evaluate,demos,testset,grasps,export_onnx}``.
"""

from regrasp_mjx.config import ConfigError, EnvConfig, SceneConfig, TaskConfig
from regrasp_mjx.geometry import grasp_pose

__version__ = "0.1.0"
__all__ = ["ConfigError", "EnvConfig", "SceneConfig", "TaskConfig", "grasp_pose", "load_policy", "__version__"]


def __getattr__(name: str):
    if name == "load_policy":  # lazy: the policy module imports the learner's networks
        from regrasp_mjx.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'regrasp_mjx' has no attribute {name!r}")
