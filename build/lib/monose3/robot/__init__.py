"""The robot: URDF kinematics, keypoints and surface points (:mod:`.model`), its triangle
meshes (:mod:`.meshes`) and the batched PyTorch renderer (:mod:`.renderer`)."""

from monose3.robot.model import (
    KUKA,
    NUM_SURFACE_POINTS,
    PANDA,
    ROBOTS,
    Keypoint,
    RobotModel,
    RobotSpec,
    get_spec,
    robot_reference,
    spec_from_files,
    spec_from_robot_file,
)

__all__ = [
    "KUKA",
    "NUM_SURFACE_POINTS",
    "PANDA",
    "ROBOTS",
    "Keypoint",
    "RobotModel",
    "RobotSpec",
    "get_spec",
    "robot_reference",
    "spec_from_files",
    "spec_from_robot_file",
]
