"""Frames of a folder or a video: the user's images with their joints and intrinsics.

Kept free of torch and pybullet so the commands can read and check a folder before any
model loads (``monose3 calibrate`` and ``monose3 track`` take the same layouts; the plain
folder layout is described in :mod:`monose3.apps.calibrate`)."""

from __future__ import annotations

import csv
import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from monose3.data.datasets import open_dataset
from monose3.data.frame import Frame
from monose3.data.inputs import load_camera, load_joints
from monose3.data.validation import check_K
from monose3.errors import Monose3Error
from monose3.geometry.camera import Intrinsics
from monose3.robot import RobotModel

log = logging.getLogger("monose3")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
JOINTS_SUFFIXES = (".joints.json", ".joints.yaml", ".joints.yml")
CAMERA_FILES = ("camera.json", "camera.yaml", "camera.yml")
IGNORED_CSV_COLUMNS = ("time", "timestamp", "stamp")
NAME_CSV_COLUMNS = ("frame", "name")


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _image_stem(name: str) -> str | None:
    low = name.lower()
    for suffix in IMAGE_SUFFIXES:
        if low.endswith(suffix):
            return name[: -len(suffix)]
    return None


def _joints_stem(name: str) -> str | None:
    low = name.lower()
    for suffix in JOINTS_SUFFIXES:
        if low.endswith(suffix):
            return name[: -len(suffix)]
    return None


def is_plain_folder(folder: Path) -> bool:
    """True when ``folder`` uses the plain layout (a camera file or ``*.joints.json`` files)."""
    names = [e.name for e in os.scandir(folder) if e.is_file()]
    return any(n in CAMERA_FILES for n in names) or any(_joints_stem(n) is not None for n in names)


def load_plain_frames(folder: str | Path, robot: RobotModel) -> list[Frame]:
    """The frames of a plain folder (layout in the module docstring); joints are read and
    checked up front so a bad file stops the run before any estimation."""
    folder = Path(folder)
    names = sorted((e.name for e in os.scandir(folder) if e.is_file()), key=_natural_key)
    camera_file = next((folder / n for n in CAMERA_FILES if n in names), None)
    images = [(n, _image_stem(n)) for n in names if _image_stem(n) is not None]
    joints_files = {_joints_stem(n): n for n in names if _joints_stem(n) is not None}
    if not images:
        raise Monose3Error(
            f"no images (.png/.jpg) in {folder}; put NNNN.png + NNNN.joints.json per frame and one camera.json there"
        )
    if camera_file is None:
        raise Monose3Error(
            f"no camera.json in {folder}; add the intrinsics as camera.json {{fx, fy, cx, cy, width, height}}"
        )
    camera: Intrinsics = load_camera(camera_file)
    check_K(camera.K, camera.size, str(camera_file))  # implausible focal length, K for another size
    frames = []
    for image_name, stem in images:
        if stem not in joints_files:
            raise Monose3Error(
                f"no joints file for image {image_name} in {folder}; add {stem}.joints.json with "
                "{joint name: radians} (or remove the image)"
            )
        joints = load_joints(folder / joints_files[stem], robot)
        frames.append(Frame(stem, camera.K, camera.size, joints, image_path=folder / image_name))
    orphans = sorted(set(joints_files) - {stem for _, stem in images})
    if orphans:
        log.warning("%d joints file(s) without an image in %s ignored (e.g. %s)", len(orphans), folder, orphans[0])
    return frames


def load_frames(folder: str | Path, robot: RobotModel) -> Sequence:
    """The frames of ``folder``: a plain folder (see the module docstring) or a DREAM /
    RoboKeyGen folder (frames then carry ground truth: ``pose`` and ``keypoints_3d``)."""
    folder = Path(folder)
    if not folder.exists():
        raise Monose3Error(f"frames folder not found: {folder}; check the path")
    if not folder.is_dir():
        raise Monose3Error(f"{folder} is not a folder; give the folder that holds the frames")
    if not any(True for _ in os.scandir(folder)):
        raise Monose3Error(
            f"frames folder {folder} is empty; put NNNN.png + NNNN.joints.json per frame and camera.json there "
            "(or point to a DREAM folder)"
        )
    if is_plain_folder(folder):
        return load_plain_frames(folder, robot)
    names = [e.name for e in os.scandir(folder) if e.is_file()]
    has_dream_json = any(n.endswith(".json") and not n.startswith("_") for n in names)
    has_subdirs = any(e.is_dir() for e in os.scandir(folder))
    if not has_dream_json and not has_subdirs:
        if any(_image_stem(n) for n in names):
            first = next(n for n in sorted(names, key=_natural_key) if _image_stem(n))
            raise Monose3Error(
                f"no joints file for image {first} in {folder}; add {_image_stem(first)}.joints.json with "
                "{joint name: radians} per image and one camera.json"
            )
        raise Monose3Error(
            f"no frames in {folder}; expected NNNN.png + NNNN.joints.json per frame and camera.json, "
            "or a DREAM folder (NNNNNN.json + NNNNNN.rgb.jpg)"
        )
    return open_dataset(folder, robot)


# ---- unusable frames: one policy ---------------------------------------------------------------


def skipped_annotations(frames: Sequence) -> list[dict]:
    """The frames a DREAM / RoboKeyGen reader left out for bad annotations, as {frame, reason}."""
    return [{"frame": str(name), "reason": str(reason)} for name, reason in getattr(frames, "skipped", [])]


def load_images(batch: Sequence, skipped: list[dict]) -> tuple[list, list[np.ndarray]]:
    """The frames of ``batch`` whose image reads, and their images; the others are appended to
    ``skipped`` (one policy for every command: skip a corrupt or missing image, name it, go on)."""
    kept, images = [], []
    for frame in batch:
        try:
            images.append(frame.load_image())
        except Monose3Error as err:
            skipped.append({"frame": str(frame.name), "reason": str(err)})
            continue
        kept.append(frame)
    return kept, images


def format_skipped(
    name: str, skipped: Sequence[dict], shown: int = 3, where: str = "the JSON's 'skipped' list"
) -> str | None:
    """The summary line of the skipped frames (None when there are none)."""
    if not skipped:
        return None
    names = ", ".join(s["frame"] for s in skipped[:shown]) + (", ..." if len(skipped) > shown else "")
    return f"{name}: skipped {len(skipped)} unusable frame(s): {names} (reasons in {where})"


# ---- per-frame joints of a video (layouts in monose3.apps.track) ---------------------------------------


def load_joints_csv(path: str | Path, robot: RobotModel) -> tuple[list[str] | None, np.ndarray]:
    """Frame names (from a ``frame``/``name`` column, else None) and joints ``[N, n]`` from a CSV
    whose header names the joints (layout in the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise Monose3Error(f"joints CSV not found: {p}; check the path")
    with p.open(newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    if len(rows) < 2:
        raise Monose3Error(f"{p} needs a header row of joint names and one row per frame; it has {len(rows)} row(s)")
    header = [h.strip() for h in rows[0]]
    lower = [h.lower() for h in header]
    name_col = next((i for i, h in enumerate(lower) if h in NAME_CSV_COLUMNS), None)
    joint_cols = [i for i, h in enumerate(lower) if i != name_col and h not in IGNORED_CSV_COLUMNS]
    if all(_is_float(h) for h in header):
        raise Monose3Error(
            f"{p} has no header row; add a first row naming the joints (e.g. {robot.required_joints[0]})"
        )
    names, joints = [], []
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise Monose3Error(f"{p} row {r} has {len(row)} values but the header has {len(header)}; fix the row")
        values = {}
        for i in joint_cols:
            cell = row[i].strip()
            if not _is_float(cell):
                raise Monose3Error(f"{p} row {r}: {header[i]} = {cell!r} is not a number (radians)")
            values[header[i]] = float(cell)
        try:
            joints.append(load_joints(values, robot))
        except Monose3Error as err:
            raise Monose3Error(f"{p} row {r}: {err}") from None
        names.append(row[name_col].strip() if name_col is not None else None)
    return (names if name_col is not None else None), np.stack(joints)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_joints_dir(folder: str | Path, robot: RobotModel) -> tuple[list[str], np.ndarray]:
    """Per-frame joint files of a folder (JSON/YAML, natural name order): names and ``[N, n]``."""
    d = Path(folder)
    if not d.is_dir():
        raise Monose3Error(f"joints folder not found: {d}; give a folder with one joints JSON per frame")
    files = sorted(
        (e.name for e in os.scandir(d) if e.is_file() and e.name.lower().endswith((".json", ".yaml", ".yml"))),
        key=_natural_key,
    )
    files = [f for f in files if not f.startswith("camera.")]
    if not files:
        raise Monose3Error(f"no joints files (.json/.yaml) in {d}; put one {{name: radians}} file per video frame")
    names = [f.split(".")[0] for f in files]
    return names, np.stack([load_joints(d / f, robot) for f in files])
