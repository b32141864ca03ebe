"""Video input: the frames of a video file (OpenCV's FFmpeg, imageio for what OpenCV cannot
open) and, with a camera file and one row of joints per frame, the frames to track."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from monose3.data.frame import Frame
from monose3.data.inputs import load_camera
from monose3.errors import Monose3Error


def read_video(path: str | Path) -> Iterator[np.ndarray]:
    """The frames of a video file as RGB uint8 arrays (OpenCV's FFmpeg; imageio/Pillow for what
    OpenCV cannot open, such as GIFs on some builds)."""
    p = Path(path)
    if not p.is_file():
        raise Monose3Error(f"video not found: {p}; check the path")
    cap = cv2.VideoCapture(str(p))
    count = 0
    try:
        while cap.isOpened():
            ok, bgr = cap.read()
            if not ok:
                break
            count += 1
            yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    finally:
        cap.release()
    if count:
        return
    import imageio.v3 as iio

    try:
        frames = iio.imiter(p)
        for frame in frames:
            img = np.asarray(frame)
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            yield np.ascontiguousarray(img[:, :, :3]).astype(np.uint8, copy=False)
            count += 1
    except Exception as err:  # noqa: BLE001 - any decoder failure means the same to the user
        if count:
            raise Monose3Error(f"video {p} is corrupt after frame {count} ({type(err).__name__})") from None
        raise Monose3Error(
            f"cannot read video {p} ({type(err).__name__}); convert it to MP4 (H.264) or a folder of PNG frames"
        ) from None
    if not count:
        raise Monose3Error(f"video {p} has no frames; check the file")


def count_video_frames(path: str | Path) -> int:
    """Number of decodable frames (counted by grabbing, not from the header, which can be wrong)."""
    cap = cv2.VideoCapture(str(path))
    n = 0
    try:
        while cap.isOpened() and cap.grab():
            n += 1
    finally:
        cap.release()
    return n if n else sum(1 for _ in read_video(path))


def video_frames(
    video: str | Path, camera_file: str | Path, joints: np.ndarray, names: Sequence[str] | None = None
) -> Iterator[Frame]:
    """The frames of a video with their joints. The camera file and the frame count are checked
    here, before anything is estimated; the frames are then decoded one at a time."""
    camera = load_camera(camera_file)
    n = count_video_frames(video)
    if n != len(joints):
        raise Monose3Error(
            f"video {Path(video).name} has {n} frames but {len(joints)} joint rows were given; "
            "give exactly one row (file) of joints per video frame"
        )

    def frames() -> Iterator[Frame]:
        for i, image in enumerate(read_video(video)):
            name = names[i] if names is not None and names[i] else f"{i:06d}"
            yield Frame(name, camera.K, camera.size, joints[i], image=image)

    return frames()
