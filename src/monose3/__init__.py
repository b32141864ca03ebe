"""monose3: markerless camera-to-robot pose estimation with MonoSE(3)-Diffusion.

The public API, imported on first use (``import monose3`` itself loads neither torch nor the
robot model, so the command line answers ``--help`` at once)::

    import monose3
    estimator = monose3.load_estimator()                   # the bundled Panda model
    image = monose3.load_image("frame.png")
    camera = monose3.load_camera("camera.json")
    joints = monose3.load_joints("joints.json", estimator.robot)
    result = monose3.estimate_pose(estimator, image, joints, camera.K)
    result.camera_from_base                                # 4x4, metres
"""

from importlib import import_module
from typing import Any

from monose3.errors import Monose3Error

__version__ = "0.1.0"

_PUBLIC = {
    "load_estimator": "monose3.api",
    "estimate_pose": "monose3.api",
    "overlay_image": "monose3.api",
    "PoseResult": "monose3.api",
    "PoseEstimator": "monose3.estimator",
    "Estimate": "monose3.estimator",
    "Tracker": "monose3.tracking",
    "TrackingPolicy": "monose3.tracking",
    "Config": "monose3.method.config",
    "get_preset": "monose3.method.config",
    "calibrate": "monose3.calibration",
    "adapt_parser": "monose3.adaptation",
    "AdaptConfig": "monose3.adaptation",
    "save_adapted_parser": "monose3.adaptation",
    "load_frames": "monose3.data.frames",
    "load_image": "monose3.data.inputs",
    "load_joints": "monose3.data.inputs",
    "load_camera": "monose3.data.inputs",
    "Intrinsics": "monose3.geometry.camera",
    "scale_camera": "monose3.geometry.camera",
    "RobotModel": "monose3.robot",
    "save_image": "monose3.report.overlays",
    "ASSETS": "monose3.api",
}
__all__ = ["Monose3Error", "__version__", *_PUBLIC]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'monose3' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
