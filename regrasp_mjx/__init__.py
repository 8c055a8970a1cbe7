"""regrasp_mjx: learned rapid motion planning for bimanual suture-needle regrasping in MuJoCo MJX.

Public entry points: :class:`regrasp_mjx.env.RegraspEnv`, :func:`regrasp_mjx.geometry.grasp_pose`,
:func:`regrasp_mjx.scene.load_scene`, :func:`regrasp_mjx.sampling.load_testset`, and the CLIs
``python -m regrasp_mjx.testset``.
"""

from regrasp_mjx.config import ConfigError, EnvConfig, SceneConfig, TaskConfig
from regrasp_mjx.geometry import grasp_pose

__version__ = "0.1.0"
__all__ = ["ConfigError", "EnvConfig", "SceneConfig", "TaskConfig", "grasp_pose", "__version__"]
