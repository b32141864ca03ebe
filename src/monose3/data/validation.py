"""One validation layer for the Python API and the commands: the same checks, the same one-line
``Monose3Error`` (problem and fix), run before any model is loaded.

This module imports neither torch nor pybullet (only numpy, the file loaders of
:mod:`monose3.data.inputs` and the URDF parser of :mod:`monose3.robot`), so a command can refuse a
bad input in well under a second. What is checked:

* joints: every layout the README documents (``{name: radians}``, a list of 7 or 8 values, a
  ``[1, 8]`` or ``[8]`` array, a DREAM frame); NaN, degrees and wrong counts are refused;
* images: an ``H x W x 3`` uint8 RGB array (grey, RGBA and float arrays are refused with the
  conversion to use, since a float image's range cannot be guessed); too small or uniform
  (all black) images are refused. BGR cannot be told from RGB: it is the caller's job
  (``monose3.data.inputs.load_image`` returns RGB);
* intrinsics: a 3x3 K with positive focal lengths that are plausible for the image's width
  (``FOCAL_RANGE``), a principal point near the image centre (a K for another image size puts
  it elsewhere);
* priors: a rigid 4x4 in metres that shows the robot in front of the camera at a plausible
  distance (a prior in millimetres puts it hundreds of metres away);
* counts (``--chains``, ``--batch-size``, ``--limit``) and output paths (a folder option that
  names an existing file, a file option that names a folder);
* checkpoints: read without torch to learn the robot they are for (so the joints can be
  checked before the model loads); a folder or a non-monose3 file is refused.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from monose3.data.inputs import check_image_camera, load_joints, pose_from_obj
from monose3.errors import Monose3Error
from monose3.geometry.camera import Intrinsics, project
from monose3.robot import RobotModel

SAMPLERS = ("fit", "revdiff", "directreg")  # "fit": perception.fitting; the others the paper's

# fx and fy in multiples of the image width: 0.1 x is a 157 deg field of view, 10 x a 5.7 deg one.
FOCAL_RANGE = (0.1, 10.0)
# The principal point may sit at most this fraction of the image size away from the centre.
PRINCIPAL_POINT_OFFSET = 0.22
# The smallest image side the network can see a robot in.
MIN_IMAGE_SIDE = 32
# A prior that puts the robot's keypoints (mean) closer or further than this is refused.
PRIOR_DISTANCE_M = (0.1, 10.0)


# ---- counts and choices ------------------------------------------------------------------------


def check_count(value: Any, name: str, minimum: int = 1, hint: str = "") -> int:
    """An integer option that must be at least ``minimum`` (``--chains``, ``--batch-size``...)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise Monose3Error(f"{name} must be a whole number, got {value!r}")
    if value < minimum:
        raise Monose3Error(f"{name} must be at least {minimum}, got {value}{hint}")
    return int(value)


def check_chains(chains: Any, name: str = "chains") -> int:
    """Number of reverse chains: 1 (no uncertainty) or more."""
    return check_count(chains, name, 1, " (1 runs a single chain without an uncertainty, 2 or more give one)")


def check_sampler(sampler: Any, allowed: Sequence[str] = SAMPLERS) -> str:
    if sampler not in allowed:
        raise Monose3Error(f"unknown sampler {sampler!r}; choose one of {', '.join(allowed)}")
    return str(sampler)


# ---- images ------------------------------------------------------------------------------------


def check_image(image: Any, source: str = "image", content: bool = True) -> np.ndarray:
    """``image`` as a contiguous ``H x W x 3`` uint8 RGB array, or a one-line error.

    ``content``: also refuse an image whose pixels are all equal (black, a lens cap)."""
    try:
        arr = np.asarray(image)
    except Exception:  # noqa: BLE001 - anything that is not array-like
        arr = np.empty(0)
    if arr.dtype == object or arr.size == 0:
        raise Monose3Error(f"{source} must be an H x W x 3 uint8 RGB array, got {type(image).__name__}")
    if arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 1):
        raise Monose3Error(
            f"{source} is a {arr.shape[1]}x{arr.shape[0]} single-channel (grayscale) array; give H x W x 3 RGB, "
            "e.g. np.repeat(gray[..., None], 3, axis=2)"
        )
    if arr.ndim == 3 and arr.shape[2] == 4:
        raise Monose3Error(f"{source} has 4 channels (RGBA); drop the alpha channel with image[..., :3]")
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise Monose3Error(f"{source} must be an H x W x 3 RGB array, got shape {arr.shape}")
    if arr.dtype != np.uint8:
        if np.issubdtype(arr.dtype, np.floating):
            raise Monose3Error(
                f"{source} is a {arr.dtype} array; give uint8 RGB 0-255 "
                "(from 0-1 floats: (image * 255).round().astype(np.uint8))"
            )
        raise Monose3Error(f"{source} has dtype {arr.dtype}; give uint8 RGB 0-255 (e.g. image.astype(np.uint8))")
    h, w = arr.shape[:2]
    if min(h, w) < MIN_IMAGE_SIDE:
        raise Monose3Error(
            f"{source} is only {w}x{h} pixels; give an image at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} "
            "in which the robot is visible"
        )
    if content and int(arr.min()) == int(arr.max()):
        raise Monose3Error(
            f"{source} is uniform (every pixel is {int(arr.min())}); check the camera (lens cap, exposure) or the file"
        )
    return np.ascontiguousarray(arr)


# ---- intrinsics --------------------------------------------------------------------------------


def check_K(K: Any, image_size: tuple[int, int], source: str = "K", plausible: bool = True) -> np.ndarray:  # noqa: N802
    """A float64 3x3 camera matrix for an image of ``image_size`` = (width, height): a valid
    pinhole camera (:meth:`Intrinsics.from_K`) and, with ``plausible``, focal lengths within
    ``FOCAL_RANGE`` x width and the principal point near the centre (a K for another image
    size, or in other units, fails these)."""
    camera = Intrinsics.from_K(K, int(image_size[0]), int(image_size[1]), source)
    if plausible:
        check_plausible(camera, source)
    return camera.K


def check_plausible(camera: Intrinsics, source: str) -> None:
    """Refuse intrinsics no real camera at this image size has (see :func:`check_K`)."""
    (lo, hi), w, h = FOCAL_RANGE, camera.width, camera.height
    for name, f in (("fx", camera.fx), ("fy", camera.fy)):
        if not lo * w <= f <= hi * w:
            raise Monose3Error(
                f"{source}: {name} = {f:g} px is implausible for a {w}-pixel-wide image (expected "
                f"{lo * w:g}-{hi * w:g}, {lo:g}-{hi:g} x the width); give the focal length in pixels, "
                f"calibrated at {w}x{h}"
            )
    cx, cy, off = camera.cx, camera.cy, PRINCIPAL_POINT_OFFSET
    if abs(cx - (w - 1) / 2) > off * w or abs(cy - (h - 1) / 2) > off * h:
        raise Monose3Error(
            f"{source}: principal point ({cx:g}, {cy:g}) is far from the centre of the {w}x{h} image, the sign of "
            f"a K for another image size; give intrinsics calibrated at {w}x{h} "
            "(for a resized image: monose3.scale_camera)"
        )


def check_camera(camera: Intrinsics, image: np.ndarray, source: str = "camera") -> np.ndarray:
    """The camera file's intrinsics against the image: same size, plausible K. Returns K."""
    check_image_camera(image, camera)
    return check_K(camera.K, camera.size, source)


# ---- joints ------------------------------------------------------------------------------------


def check_joints(joints: Any, robot: RobotModel, source: str = "joints") -> np.ndarray:
    """One configuration as a vector in ``robot.joint_names`` order (radians).

    Accepts a file path, ``{name: radians}``, a list / array of the arm's joints (7 for the
    Panda, the gripper defaulted) or of all joints (8), shape ``[n]`` or ``[1, n]``, and
    DREAM's layouts; refuses NaN, degrees, unknown names and wrong counts."""
    if isinstance(joints, (str, Path, Mapping)):
        return load_joints(joints, robot)
    if isinstance(joints, (list, tuple)) and joints and all(isinstance(j, Mapping) for j in joints):
        return load_joints(list(joints), robot)  # DREAM's [{name, position}, ...]
    try:
        arr = np.asarray(joints, dtype=np.float64)
    except (TypeError, ValueError):
        raise Monose3Error(
            f"{source} must be {{name: radians}} or {len(robot.required_joints)} numbers in URDF order, got {joints!r}"
        ) from None
    if arr.ndim == 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 1:
        raise Monose3Error(
            f"{source} must be one configuration ({len(robot.required_joints)} or {len(robot.joint_names)} values), "
            f"got shape {arr.shape}; pass one frame's joints"
        )
    return load_joints([float(v) for v in arr], robot)


def check_joint_batch(joints: Any, robot: RobotModel, count: int) -> np.ndarray:
    """``[B, n]`` joints for ``count`` images (rows in any layout :func:`check_joints` takes)."""
    if isinstance(joints, np.ndarray) and joints.ndim == 1 and count == 1:
        joints = joints[None]
    rows = list(joints) if not isinstance(joints, Mapping) else [joints]
    if len(rows) != count:
        raise Monose3Error(
            f"got joints for {len(rows)} frame(s) but {count} image(s); give one row of joints per image"
        )
    return np.stack([check_joints(r, robot, f"joints of frame {i}") for i, r in enumerate(rows)])


# ---- priors ------------------------------------------------------------------------------------


def check_prior(
    prior: Any, robot: RobotModel, joints: np.ndarray, K: np.ndarray, image_size: tuple[int, int], source: str = "prior"
) -> np.ndarray:
    """A camera-from-base prior that is rigid, in metres, and shows the robot in the image."""
    pose = pose_from_obj(prior, source)
    points = robot.keypoints(np.asarray(joints, np.float64)[None], pose[None])[0]
    centre = points.mean(0)
    dist = float(np.linalg.norm(centre))
    lo, hi = PRIOR_DISTANCE_M
    if dist > hi:
        hint = " (it looks like millimetres: divide the translation by 1000)" if lo <= dist / 1000 <= hi else ""
        raise Monose3Error(
            f"{source} puts the robot {dist:.4g} m from the camera, more than {hi:g} m{hint}; give camera_from_base "
            "in metres"
        )
    if dist < lo:
        raise Monose3Error(
            f"{source} puts the robot {dist:.3g} m from the camera, less than {lo:g} m; give camera_from_base in metres"
        )
    w, h = image_size
    u, v = project(centre[None], np.asarray(K, np.float64))[0] if centre[2] > 0 else (-1.0, -1.0)
    if not (0 <= u < w and 0 <= v < h):
        raise Monose3Error(
            f"{source}: the prior pose puts the robot outside the image; give camera_from_base (not its inverse), "
            "in metres"
        )
    return pose


# ---- one estimate, one batch ------------------------------------------------------------------


def check_estimate_inputs(
    image: Any, joints: Any, K: Any, robot: RobotModel, prior: Any = None, chains: Any = 1, sampler: str = "revdiff"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, int]:
    """Everything ``estimate_pose`` and ``monose3 estimate`` need, checked: image, joints, K,
    prior (or None), chains."""
    chains = check_chains(chains)
    check_sampler(sampler)
    image = check_image(image)
    h, w = image.shape[:2]
    K = check_K(K, (w, h))
    q = check_joints(joints, robot)
    pose = None if prior is None else check_prior(prior, robot, q, K, (w, h))
    return image, q, K, pose, chains


def check_batch(
    images: Any, Ks: Any, joints: Any, robot: RobotModel
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The structural checks of ``PoseEstimator.estimate`` / ``track`` (no plausibility
    limits, so any dataset passes): images, ``[B, 3, 3]`` Ks and ``[B, n]`` joints agree."""
    if isinstance(images, np.ndarray) and images.ndim == 3:
        raise Monose3Error("images must be a list of H x W x 3 arrays (one per frame); wrap one image as [image]")
    images = [check_image(im, f"image {i}", content=False) for i, im in enumerate(images)]
    if not images:
        raise Monose3Error("no images given; pass a list with at least one H x W x 3 RGB array")
    Ks = np.asarray(Ks, dtype=np.float64)
    if Ks.ndim == 2 and len(images) == 1:
        Ks = Ks[None]
    if Ks.shape != (len(images), 3, 3):
        raise Monose3Error(f"Ks must be [{len(images)}, 3, 3] (one K per image), got shape {Ks.shape}")
    for i, (im, K) in enumerate(zip(images, Ks, strict=True)):
        check_K(K, (im.shape[1], im.shape[0]), f"K of image {i}", plausible=False)
    return images, Ks, check_joint_batch(joints, robot, len(images))


def check_pose_batch(poses: Any, n: int, name: str) -> np.ndarray:
    """``[n, 4, 4]`` camera-from-base poses (e.g. tracking's previous estimates), each finite and rigid."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (n, 4, 4):
        raise Monose3Error(f"{name} must be [{n}, 4, 4] (one camera-from-base pose per image), got shape {poses.shape}")
    return np.stack([pose_from_obj(p, f"{name} {i}") for i, p in enumerate(poses)])


# ---- output paths ------------------------------------------------------------------------------


def _check_parents(p: Path, option: str) -> None:
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise Monose3Error(f"{option} {p}: {parent} is a file, not a folder; choose another path")
            if not os.access(parent, os.W_OK):
                raise Monose3Error(f"{option} {p}: cannot write in {parent} (permission denied); choose another path")
            return


def check_output_dir(path: str | Path, option: str = "--out") -> Path:
    """A folder to write into (created if missing): refuse an existing file, before any work."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise Monose3Error(f"{option} {p} is an existing file, not a folder; give a folder path (created if missing)")
    if p.is_dir() and not os.access(p, os.W_OK):
        raise Monose3Error(f"{option} {p}: cannot write in this folder (permission denied); choose another")
    _check_parents(p, option)
    return p


def check_output_file(path: str | Path, option: str, suffixes: Sequence[str] = ()) -> Path:
    """A file to write (replaced atomically if it exists): refuse a folder or a bad extension."""
    p = Path(path)
    if p.is_dir():
        example = p / ("out" + (suffixes or [".json"])[0])
        raise Monose3Error(f"{option} {p} is a folder; give a file path such as {example}")
    if suffixes and p.suffix.lower() not in suffixes:
        raise Monose3Error(f"{option} {p}: unsupported extension {p.suffix!r}; use {' or '.join(suffixes)}")
    _check_parents(p, option)
    return p


def check_input_dir(path: str | Path, option: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise Monose3Error(f"{option} {p} not found; check the path")
    if not p.is_dir():
        raise Monose3Error(f"{option} {p} is not a folder; give the folder that holds the frames")
    return p
