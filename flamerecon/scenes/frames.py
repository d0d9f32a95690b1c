"""One camera's frame, read from a video file or from a folder of numbered images.

A camera named ``NAME`` (or ``NAME.mp4``, as PINF's ``file_name`` writes it) finds its frame
``n`` in the first of these that exists under the scene folder:

- the named file itself when it is a video (``NAME.mp4``, ``.avi``, ``.mov``, ``.mkv``);
- a folder ``NAME/`` holding ``NNNNNN.png`` (six digits, any common image extension);
- a video ``NAME.<ext>`` for the extensions above.

Images come back as float32 arrays (H, W, C) in [0, 1], C = 1 (grayscale) or 3 (RGB);
an alpha channel is composited over black (the emission model's empty background). Every image
is read as displayed: its EXIF orientation applied (JPEG, PNG, WebP, TIFF; as viewers and
``cv2.imread`` show it, :mod:`flamerecon.scenes.orientation`), so the calibration must be of the
images as displayed (a size that disagrees is refused naming the orientation); file
extensions match in either case (``train00.MP4``); a 16-bit image holding only 8-bit values is
refused (it would read 257 times too dark), and so is an OpenEXR frame this OpenCV cannot read,
with the reason.
"""

from __future__ import annotations

import errno
import functools
import os
from pathlib import Path

import cv2
import numpy as np

from flamerecon.native import native_stderr_silenced
from flamerecon.scenes.base import SceneError
from flamerecon.scenes.orientation import TURNS, displayed, exif_orientation

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".pgm", ".ppm")


def _to_float_rgb(raw: np.ndarray, path: Path) -> np.ndarray:
    """Decoded OpenCV array (H, W[, C]) in BGR(A) -> float32 (H, W, 1 or 3) RGB in [0, 1]."""
    if raw.dtype == np.uint8:
        img = raw.astype(np.float32) / 255.0
    elif raw.dtype == np.uint16:
        if 0 < int(raw.max()) <= 255:
            raise SceneError(f"{path}: a 16-bit image whose brightest value is {int(raw.max())} of 65535: 8-bit values "
                             "saved in 16 bits, which read 257 times too dark; save it as 8-bit, or scale it to 16 bits")
        img = raw.astype(np.float32) / 65535.0
    elif raw.dtype in (np.float32, np.float64):
        img = raw.astype(np.float32)
    else:
        raise SceneError(f"{path}: pixel type {raw.dtype} is not supported (uint8, uint16, float)")
    if img.ndim == 2:
        img = img[:, :, None]
    channels = img.shape[2]
    if channels == 4:
        img = img[:, :, :3] * img[:, :, 3:4]
    elif channels == 2:
        img = img[:, :, :1] * img[:, :, 1:2]
    if img.shape[2] == 3:
        img = img[:, :, ::-1]
    if not np.isfinite(img).all():
        raise SceneError(f"{path}: pixel values: the image holds NaN or Inf")
    return np.ascontiguousarray(img)


def read_image(path: str | Path) -> np.ndarray:
    """Decode one image file to float32 (H, W, C) in [0, 1] (alpha composited over black)."""
    path = Path(path)
    if not path.is_file():
        refuse_link_loop(path)
        raise SceneError(f"{path}: image file not found")
    orientation = exif_orientation(path)
    tiff = path.suffix.lower() in (".tif", ".tiff")  # OpenCV's TIFF decoder turns it itself (or fails)
    with native_stderr_silenced():  # libpng and friends print their own complaint
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # as stored: bit depth and alpha kept
    if raw is None or raw.size == 0:
        if path.suffix.lower() == ".exr" and openexr_missing():
            raise SceneError(f"{path}: {openexr_missing()}")
        if tiff and orientation != 1:
            raise SceneError(f"{path}: a TIFF whose orientation tag says {orientation} ({TURNS[orientation]}), which "
                             f"this OpenCV ({cv2.__version__}) cannot read; save the frame upright (orientation 1) or "
                             "as PNG")
        raise SceneError(f"{path}: cannot decode the image (corrupt file or unknown format)")
    return _to_float_rgb(raw if tiff else displayed(raw, orientation), path)


@functools.cache
def openexr_missing() -> str | None:
    """Why this OpenCV cannot read OpenEXR files (None where it can): a build without the
    codec, or one that reads it only with ``OPENCV_IO_ENABLE_OPENEXR=1`` set."""
    build = [line for line in cv2.getBuildInformation().splitlines() if "OpenEXR" in line]
    if not build or any(line.split(":")[-1].strip().upper().startswith("NO") for line in build):
        return (f"this OpenCV ({cv2.__version__}) is built without OpenEXR, so it cannot read .exr files; convert "
                "the frames to 32-bit float TIFF or 16-bit PNG")
    if os.environ.get("OPENCV_IO_ENABLE_OPENEXR", "").lower() not in ("1", "true", "on", "yes"):
        return ("OpenCV reads .exr files only with OPENCV_IO_ENABLE_OPENEXR=1 in the environment (off by default); "
                "set it and run again, or convert the frames to 32-bit float TIFF or 16-bit PNG")
    return None


def video_length(path: str | Path) -> int:
    """Number of frames a video holds, counted by decoding (container counts can lie)."""
    path = Path(path)
    with native_stderr_silenced():  # ffmpeg prints its own complaint (moov atom not found, ...)
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise SceneError(f"{path}: cannot open the video (corrupt file or unsupported codec)")
            count = 0
            while cap.grab():
                count += 1
            return count
        finally:
            cap.release()


def read_video_frame(path: str | Path, frame: int) -> np.ndarray:
    """Decode frame ``frame`` (0-based) of a video to float32 (H, W, C) in [0, 1].

    Frames are decoded in order from the start rather than seeked, which is exact for every
    codec (seeking lands on key frames for some).
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: video file not found")
    if frame < 0:
        raise SceneError(f"{path}: frame {frame}: frame index must be >= 0")
    with native_stderr_silenced():  # ffmpeg prints its own complaint (moov atom not found, ...)
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise SceneError(f"{path}: cannot open the video (corrupt file or unsupported codec)")
            for index in range(frame + 1):
                if not cap.grab():
                    if index == 0:
                        raise SceneError(f"{path}: cannot decode any frame of the video")
                    raise SceneError(
                        f"{path}: frame {frame}: beyond the end of the video ({index} frames)"
                    )
            ok, raw = cap.retrieve()
        finally:
            cap.release()
    if not ok or raw is None:
        raise SceneError(f"{path}: frame {frame}: cannot decode this frame")
    return _to_float_rgb(raw, path)


def is_link_loop(path: str | Path) -> bool:
    """Whether ``path`` is a symbolic link that never resolves (a loop: ELOOP)."""
    try:
        os.stat(path)
    except OSError as err:
        return err.errno == errno.ELOOP
    return False


def refuse_link_loop(*paths: str | Path) -> None:
    """SceneError naming the first of ``paths`` that is a symbolic link loop."""
    for path in paths:
        if is_link_loop(path):
            raise SceneError(
                f"{path}: a symbolic link loop (following it leads back to itself); point the link "
                "at the real video, image or frame folder"
            )


def printable(name: str, where: str) -> str:
    """``name`` (a camera's name, a path) when it holds no control character, else a SceneError
    at ``where``: a NUL cannot be in a file name (the OS would refuse it in a ValueError)."""
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in str(name)):
        raise SceneError(f"{where}: {str(name)!r} holds a control character (NUL, newline, tab, ...), which no file "
                         "name here can hold; name it with printable characters only")
    return name


def frame_source(root: str | Path, name: str) -> Path:
    """The video file or frame folder holding camera ``name``'s frames under ``root``."""
    root = Path(root)
    printable(name, f"{root}: camera name")
    direct = root / name
    stem = Path(name).stem if Path(name).suffix.lower() in VIDEO_EXTENSIONS else name
    refuse_link_loop(direct, root / stem, *(root / f"{stem}{ext}" for ext in VIDEO_EXTENSIONS))
    if direct.is_file() and direct.suffix.lower() in VIDEO_EXTENSIONS:
        return direct
    folder = root / stem
    if folder.is_dir():
        return folder
    for ext in VIDEO_EXTENSIONS:
        for video in (root / f"{stem}{ext}", root / f"{stem}{ext.upper()}"):
            if video.is_file():
                return video
    raise SceneError(
        f"{root}: camera '{name}': found neither a video {stem}.mp4 (or "
        f"{'/'.join(VIDEO_EXTENSIONS[1:])}) nor a folder of frames {stem}/"
    )


def frame_file(folder: Path, frame: int) -> Path:
    """The image of frame ``frame`` in a folder of numbered frames (``000059.png``, ``59.png``)."""
    for stem in (f"{frame:06d}", str(frame)):
        for ext in IMAGE_EXTENSIONS:
            for candidate in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
                if candidate.is_file():
                    return candidate
    have = sorted(p.stem for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    listing = (
        f"frames {', '.join(have[:6])}{', ...' if len(have) > 6 else ''}" if have else "no images"
    )
    raise SceneError(f"{folder}: frame {frame}: no file {frame:06d}.png there (it has {listing})")


def source_frames(path: str | Path) -> list[int] | None:
    """The frame numbers the source of a frame read from ``path`` holds, in order: 0 to a
    video's frame count less one (its container's count, not decoded), the numbers of the
    numbered images beside a frame of a frame folder (50, 51, 53: a gap stays a gap); None for
    an image on its own, which any frame number reads."""
    path = Path(path)
    if path.suffix.lower() in VIDEO_EXTENSIONS:
        with native_stderr_silenced():
            cap = cv2.VideoCapture(str(path))
            try:
                return list(range(max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 1)))
            finally:
                cap.release()
    if path.stem.isdigit():
        return sorted({int(p.stem) for p in path.parent.iterdir()
                       if p.stem.isdigit() and p.suffix.lower() in IMAGE_EXTENSIONS})
    return None


def read_camera_frame(root: str | Path, name: str, frame: int) -> tuple[np.ndarray, Path]:
    """Frame ``frame`` of camera ``name``: (image (H, W, C) float32 in [0, 1], its file)."""
    source = frame_source(root, name)
    if source.is_dir():
        path = frame_file(source, frame)
        return read_image(path), path
    return read_video_frame(source, frame), source


def read_path_frame(base: str | Path, relpath: str, frame: int) -> tuple[np.ndarray, Path]:
    """Frame ``frame`` of whatever ``relpath`` (relative to ``base``) names: an image file (the
    frame number is then ignored), an image named without its extension (NeRF's
    ``./train/r_0``), a video, or a folder of numbered frames."""
    path = Path(base) / printable(relpath, f"{base}: image path")
    refuse_link_loop(path, *(path.with_name(path.name + ext) for ext in IMAGE_EXTENSIONS))
    if path.is_dir():
        file = frame_file(path, frame)
        return read_image(file), file
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            return read_video_frame(path, frame), path
        return read_image(path), path
    for ext in IMAGE_EXTENSIONS:
        for candidate in (path.with_name(path.name + ext), path.with_name(path.name + ext.upper())):
            if candidate.is_file():
                return read_image(candidate), candidate
    raise SceneError(f"{path}: image file not found")
