"""Converters from other calibration formats into an OpenCV calibration file that
``scene=opencv`` loads (:mod:`flamerecon.scenes.opencv_calib`; docs/own_capture.md):

- PINF / HyFluid ``info.json`` (:mod:`flamerecon.scenes.pinf`): camera_angle_x, camera_hw and the
  OpenGL camera->world ``transform_matrix`` per camera, the box from ``voxel_matrix`` and
  ``voxel_scale``, ``test_videos`` as the held-out cameras;
- COLMAP's text model (``cameras.txt``, ``images.txt``): intrinsics by camera model (pinhole and
  OpenCV-style radial/tangential distortion), world->camera quaternion and translation per image.

The file written is plain YAML: ``cameras`` (name, K, dist, R, t with x_cam = R x_world + t,
width, height, image relative to the file), and ``bbox`` / ``holdout`` where known. K follows
OpenCV's pixel convention (pixel index k at coordinate k); COLMAP's (pixel centres at k + 0.5)
and PINF's principal point are shifted to it here, and the loader shifts back.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import yaml

from flamerecon.outputs.atomic import atomic_write_text
from flamerecon.scenes.base import SceneError
from flamerecon.scenes.calibration import check_rigid, read_json_object
from flamerecon.scenes.pinf import _camera_entries, pinf_box
from flamerecon.scenes.values import FIELD_OF_VIEW, read_float, read_size, read_text

#: COLMAP camera model -> (its parameter names, OpenCV distortion from them)
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), ()),
    "PINHOLE": (("fx", "fy", "cx", "cy"), ()),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k1"), ("k1",)),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), ("k1", "k2")),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
                    ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}


def _relative(target: Path, start: Path) -> str:
    return Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()


def _camera(name: str, K: np.ndarray, w2c: np.ndarray, width: int, height: int, image: Path, out: Path,
            dist: list[float] | None = None) -> dict:
    entry = {"name": name, "K": np.asarray(K, float).round(10).tolist(), "R": w2c[:3, :3].round(12).tolist(),
             "t": w2c[:3, 3].round(12).tolist(), "width": int(width), "height": int(height),
             "image": _relative(image, out.parent)}
    if dist and any(dist):
        entry["dist"] = [float(d) for d in dist]
    return entry


def pinf_to_opencv(info: str | os.PathLike, out: str | os.PathLike) -> dict:
    """The OpenCV calibration of a PINF/HyFluid capture (``info``: its info.json or folder) as
    a dict, each camera's ``image`` its video (or frame folder) relative to ``out``."""
    data, path = read_json_object(Path(info), "info.json", "train_videos / test_videos")
    out = Path(out)
    cameras, holdout = [], []
    for where, entry, held in _camera_entries(data, path):
        if not isinstance(entry, dict):
            raise SceneError(f"{path}: {where}: must be an object")
        file_name = read_text(entry.get("file_name"), path, f"{where}.file_name")
        H, W = read_size(entry.get("camera_hw"), path, f"{where}.camera_hw", "[H, W]")
        angle = read_float(entry.get("camera_angle_x"), path, f"{where}.camera_angle_x", FIELD_OF_VIEW)
        c2w = check_rigid(entry.get("transform_matrix"), path, f"{where}.transform_matrix")
        focal = 0.5 * W / math.tan(0.5 * angle)
        K = np.array([[focal, 0.0, 0.5 * W], [0.0, focal, 0.5 * H], [0.0, 0.0, 1.0]])  # OpenCV's pixel convention
        w2c = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))  # as opengl_c2w_to_opencv_w2c, in float64
        video = path.parent / file_name
        image = video if video.exists() or not video.with_suffix("").is_dir() else video.with_suffix("")
        name = Path(file_name).stem
        cameras.append(_camera(name, K, w2c, W, H, image, out))
        if held:
            holdout.append(name)
    record: dict = {"cameras": cameras}
    box = pinf_box(data, path)
    if box is not None:
        record["bbox"] = [list(box[0]), list(box[1])]
    if holdout:
        record["holdout"] = holdout
    return record


def _colmap_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of a COLMAP text file, comments and blank lines left out."""
    if not path.is_file():
        raise SceneError(f"{path}: not found (COLMAP's text model: cameras.txt and images.txt; "
                         "colmap model_converter --output_type TXT writes them from a binary model)")
    return [(n, line.split()) for n, line in enumerate(path.read_text().splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def _numbers(fields: list[str], path: Path, line: int, what: str) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError:
        raise SceneError(f"{path}: line {line}: {what}: expected numbers, got {' '.join(fields)}") from None


def read_colmap_cameras(path: Path) -> dict[str, tuple[np.ndarray, list[float], int, int]]:
    """COLMAP's ``cameras.txt``: {camera id: (K in OpenCV's pixel convention, OpenCV
    distortion, width, height)}."""
    cameras = {}
    for line, fields in _colmap_lines(path):
        if len(fields) < 4:
            raise SceneError(f"{path}: line {line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id, model = fields[0], fields[1]
        if model not in COLMAP_MODELS:
            raise SceneError(f"{path}: line {line}: camera model {model} is not supported; use one of "
                             f"{sorted(COLMAP_MODELS)} (colmap image_undistorter makes PINHOLE images)")
        names, distortion = COLMAP_MODELS[model]
        width, height, *params = _numbers(fields[2:], path, line, "WIDTH HEIGHT PARAMS")
        if len(params) != len(names):
            raise SceneError(f"{path}: line {line}: {model} takes {len(names)} parameters "
                             f"({' '.join(names)}), got {len(params)}")
        p = dict(zip(names, params))
        fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
        K = np.array([[fx, 0.0, p["cx"] - 0.5], [0.0, fy, p["cy"] - 0.5], [0.0, 0.0, 1.0]])
        # OpenCV's order k1 k2 p1 p2 [k3 k4 k5 k6], the terms a model lacks 0
        dist = ([p.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")] + [p[k] for k in ("k3", "k4", "k5", "k6") if k in p]
                if distortion else [])
        cameras[camera_id] = (K, dist, int(width), int(height))
    if not cameras:
        raise SceneError(f"{path}: no camera")
    return cameras


def quaternion_matrix(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """A (w, x, y, z) quaternion (COLMAP's, viser's), normalised, as a rotation matrix (3, 3)."""
    q = np.array([qw, qx, qy, qz], float)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def colmap_to_opencv(model: str | os.PathLike, images: str | os.PathLike, out: str | os.PathLike) -> dict:
    """The OpenCV calibration of a COLMAP text model (``model``: the folder of cameras.txt and
    images.txt) as a dict: one camera per image, named by the image's file stem, its ``image``
    the file in ``images`` relative to ``out``."""
    model, images, out = Path(model), Path(images), Path(out)
    intrinsics = read_colmap_cameras(model / "cameras.txt")
    path = model / "images.txt"
    lines = _colmap_lines(path)
    cameras, names = [], set()
    # images.txt: two lines per image, the pose line and its 2D points (which may be empty, and
    # then dropped with the blank lines): a pose line has 10 fields and ends in a file name
    for line, fields in lines:
        if len(fields) != 10 or not Path(fields[9]).suffix:
            continue
        qw, qx, qy, qz, tx, ty, tz = _numbers(fields[1:8], path, line, "QW QX QY QZ TX TY TZ")
        if fields[8] not in intrinsics:
            raise SceneError(f"{path}: line {line}: CAMERA_ID {fields[8]} is not in {model / 'cameras.txt'}")
        K, dist, width, height = intrinsics[fields[8]]
        name = Path(fields[9]).stem
        if name in names:
            raise SceneError(f"{path}: line {line}: camera name {name!r} (the image's stem) appears twice")
        names.add(name)
        w2c = np.eye(4)
        w2c[:3, :3] = quaternion_matrix(qw, qx, qy, qz)
        w2c[:3, 3] = [tx, ty, tz]
        cameras.append(_camera(name, K, w2c, width, height, images / fields[9], out, dist))
    if not cameras:
        raise SceneError(f"{path}: no image pose line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
    return {"cameras": cameras}


def write_calibration(path: str | os.PathLike, record: dict, source: str) -> Path:
    """Write a converted calibration as YAML (whole or not at all), a comment naming ``source``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    head = (f"# converted from {source} by flamerecon (scripts/convert_capture.py); OpenCV conventions:\n"
            "# x_cam = R x_world + t, K with pixel index k at coordinate k; image: relative to this file\n")
    atomic_write_text(path, head + yaml.safe_dump(record, sort_keys=False, default_flow_style=None, width=100))
    return path
