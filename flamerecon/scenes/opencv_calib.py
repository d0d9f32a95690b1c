"""OpenCV calibrations: per camera K, distortion, and world->camera R (or rvec) and t.

One file (``cv2.FileStorage`` YAML/XML, or JSON) holding ``cameras``, a list of maps (each with
``name``) or a map from name to camera; or a folder with one such file per camera (the name is
the file's stem). Per camera, with the spellings OpenCV's samples use:

- ``K`` | ``camera_matrix`` | ``cameraMatrix``: 3x3, OpenCV pixel convention (index k at k);
- ``dist`` | ``D`` | ``distortion_coefficients`` | ``distCoeffs``: optional, 4-14 values;
- ``R`` (3x3) or ``rvec`` (Rodrigues, 3), and ``t`` | ``T`` | ``tvec`` (3): x_cam = R x_world + t;
- ``width``/``height`` | ``image_width``/``image_height`` | ``image_size`` [w, h]: optional,
  checked against the image;
- ``image``: optional path (image, video or frame folder) relative to the file; by default
  the camera's frames are found by name (``NAME.mp4`` or ``NAME/NNNNNN.png``).

Optional at the top level: ``bbox`` [[min xyz], [max xyz]] and ``holdout`` (view names).
Images are undistorted with ``cv2.undistort`` at native resolution, keeping K; the scene's K
is shifted by +0.5 to flamerecon's pixel centres.

Config (``scene`` node): ``root`` (the file or the folder), ``calibration`` (file or folder
name inside ``root``; default: the first of calibration.yaml/.yml/.xml/.json), ``frame``,
``downscale``, ``channels``, ``gamma``, ``black_level``, ``bbox``, ``holdout``, ``silhouette``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import yaml

from flamerecon.arguments import one_or_many
from flamerecon.plain import json_value
from flamerecon.scenes import register_scene
from flamerecon.scenes.base import Scene, SceneError
from flamerecon.scenes.calibration import (
    CAPTURE_KEYS,
    box_from_value,
    check_image_size,
    check_intrinsics,
    check_rotation,
    distortion,
    file_conventions,
    make_scene,
    option,
    resolve_root,
    undistort,
)
from flamerecon.scenes.frames import read_camera_frame, read_path_frame
from flamerecon.scenes.values import (
    read_array,
    read_int,
    read_matrix,
    read_names,
    read_size,
    read_text,
    refuse,
)

CALIBRATION_SUFFIXES = (".yaml", ".yml", ".xml", ".json")
_ALIASES = {
    "K": ("K", "camera_matrix", "cameraMatrix"),
    "dist": ("dist", "D", "distortion_coefficients", "distCoeffs"),
    "R": ("R",),
    "rvec": ("rvec",),
    "t": ("t", "T", "tvec"),
    "width": ("width", "image_width"),
    "height": ("height", "image_height"),
    "image_size": ("image_size",),
}


def _from_file_node(node: cv2.FileNode, file, field: str = ""):
    """A cv2.FileNode as plain Python: maps, lists, numbers, strings; an ``opencv-matrix`` (or
    ``opencv-nd-matrix``) as a float64 array of its sizes, read and checked here (a truncated
    or inconsistent one is a SceneError naming ``field``, never OpenCV's own error)."""
    if node.isNone():
        return None
    if node.isMap():
        keys = node.keys()
        value = {k: _from_file_node(node.getNode(k), file, f"{field}.{k}" if field else k) for k in keys}
        return _opencv_matrix(value, file, field) if _is_matrix(value) else value
    if node.isSeq():
        return [_from_file_node(node.at(i), file, f"{field}[{i}]") for i in range(node.size())]
    if node.isString():
        if node.string() == "...":  # what OpenCV's YAML reader gives where the file ends early
            raise SceneError(f"{file}: {field}: the file ends before this value; is it cut short?")
        return node.string()
    if node.isInt():
        return int(node.real())
    return node.real()


def _is_matrix(value: dict) -> bool:
    """Whether a map is an OpenCV matrix (cut short too: no camera field has these names)."""
    return {"rows", "cols"} <= set(value) or "sizes" in value or {"dt", "data"} <= set(value)


def _opencv_matrix(value: dict, file, field: str) -> np.ndarray:
    """An ``opencv-matrix`` map {rows, cols, dt, data} (or ``opencv-nd-matrix`` {sizes, dt,
    data}) as a float64 array: sizes from their fields, ``data`` holding exactly their
    product times the channels of ``dt`` (``3d``: 3) numbers."""
    if "sizes" in value:
        sizes = [read_int(n, file, f"{field}.sizes[{i}]") for i, n in enumerate(one_or_many(value["sizes"]))]
    else:
        sizes = [read_int(value.get(k), file, f"{field}.{k}") for k in ("rows", "cols")]
    dt = value.get("dt")
    if not isinstance(dt, str) or not re.fullmatch(r"\d*[ucwsifdh]", dt):
        raise refuse(dt, file, f"{field}.dt", "an OpenCV element type such as d, f or 3d")
    channels = int(dt[:-1] or 1)
    data = value.get("data")  # a FileStorage sequence of one number reads back as the number
    data = read_array(None if data is None else one_or_many(data), file, f"{field}.data").reshape(-1)
    want = math.prod(sizes) * channels
    if data.size != want:
        raise SceneError(f"{file}: {field}.data: holds {data.size} numbers but {field} is "
                         f"{'x'.join(map(str, sizes))} with {channels} channel(s), {want} numbers; the file "
                         "is truncated or was edited inconsistently")
    return data.reshape(*sizes, channels) if channels > 1 else data.reshape(sizes)


def read_calibration_file(path: Path) -> dict:
    """Parse a YAML/XML (cv2.FileStorage, or plain YAML) or JSON calibration into a dict."""
    suffix = path.suffix.lower()
    if suffix == ".json":
        try:
            data = json_value(path.read_text())
        except (ValueError, OSError) as err:
            raise SceneError(f"{path}: not valid JSON ({err})") from None
    else:
        with open(path, "rb") as f:
            head = f.read(16)
        if suffix == ".xml" or head.startswith(b"%YAML"):
            data = _read_file_storage(path)
        else:
            try:
                with open(path) as f:
                    data = yaml.safe_load(f)
            except yaml.YAMLError as err:
                raise SceneError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
            except RecursionError:
                raise SceneError(f"{path}: not valid YAML (nested too deeply to read)") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: top level must be a map")
    return data


def _read_file_storage(path: Path) -> dict:
    """A file cv2.FileStorage wrote (YAML or XML) as plain Python; one it cannot parse (cut
    short, malformed) is a SceneError naming the file."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # OpenCV's parse errors surface as either
        text = " ".join(str(err.__cause__ or err).split())
        where = re.search(r"\((\d+)\): (.*?)'?$", text)
        cause = f"line {where[1]}: {where[2]}" if where else text[-120:]
        raise SceneError(f"{path}: cv2.FileStorage cannot parse it ({cause}); is it cut short or malformed?") from None
    try:
        if not fs.isOpened():
            raise SceneError(f"{path}: cv2.FileStorage cannot open it")
        return _from_file_node(fs.root(), path)
    finally:
        fs.release()


def _get(entry: dict, key: str):
    for alias in _ALIASES[key]:
        if alias in entry:
            return alias, entry[alias]
    return _ALIASES[key][0], None


def _camera_list(root: Path, calibration) -> tuple[list[tuple[str, dict, Path, str]], dict, Path]:
    """(name, entry, file, field prefix) per camera, the top-level map, and the calibration path."""
    if root.is_file():
        path = root
    elif calibration:
        path = root / str(calibration)
    else:
        found = [
            root / f"calibration{s}"
            for s in CALIBRATION_SUFFIXES
            if (root / f"calibration{s}").is_file()
        ]
        if not found:
            raise SceneError(f"{root}: no calibration.yaml/.yml/.xml/.json (set scene.calibration)")
        path = found[0]
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in CALIBRATION_SUFFIXES)
        if not files:
            raise SceneError(f"{path}: no per-camera calibration files (*.yaml, *.xml, *.json)")
        return [(p.stem, read_calibration_file(p), p, "") for p in files], {}, path
    if not path.is_file():
        raise SceneError(f"{path}: calibration file not found")
    data = read_calibration_file(path)
    cameras = data.get("cameras")
    if isinstance(cameras, dict) and "name" in cameras:
        cameras = [cameras]  # an XML sequence of one camera reads back as that camera
    if isinstance(cameras, dict):
        items = [(str(k), v, f"cameras.{k}.") for k, v in cameras.items()]
    elif isinstance(cameras, list) and cameras:
        items = []
        for i, v in enumerate(cameras):
            if not isinstance(v, dict) or v.get("name") is None:
                raise SceneError(f"{path}: cameras[{i}].name: missing")
            items.append((read_text(v["name"], path, f"cameras[{i}].name"), v, f"cameras[{i}]."))
    else:
        raise SceneError(f"{path}: cameras: missing or empty (a list of camera maps)")
    for _, v, where in items:
        if not isinstance(v, dict):
            raise SceneError(f"{path}: {where.rstrip('.')}: must be a map")
    return [(name, v, path, where) for name, v, where in items], data, path


#: degrees by which a camera's R and rvec, both given, may differ (the rounding of a written file)
R_RVEC_AGREE_DEG = 0.01


def _pose(entry: dict, file, where: str) -> np.ndarray:
    """OpenCV world->camera 4x4 from R or rvec (both: they must be one rotation), and t."""
    key, R = _get(entry, "R")
    r_key, rvec = _get(entry, "rvec")
    if R is not None:
        R = check_rotation(R, file, f"{where}{key}")
    elif rvec is None:
        raise SceneError(f"{file}: {where}R: missing (give R or rvec)")
    if rvec is not None:
        from_rvec = cv2.Rodrigues(read_matrix(rvec, (3,), file, f"{where}{r_key}"))[0]
        if R is not None:
            apart = np.degrees(np.arccos(np.clip((np.trace(R.T @ from_rvec) - 1) / 2, -1.0, 1.0)))
            if apart > R_RVEC_AGREE_DEG:
                raise SceneError(f"{file}: {where}{key} and {where}{r_key} disagree: they are rotations {apart:.3g} "
                                 f"degrees apart; give one of them (or both of one rotation)")
        R = from_rvec if R is None else R
    key, t = _get(entry, "t")
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = read_matrix(t, (3,), file, f"{where}{key}")
    return w2c


def _expected_size(entry: dict, file, where: str) -> tuple[int, int] | None:
    """(H, W) the calibration states, or None."""
    key, size = _get(entry, "image_size")
    if size is not None:
        w, h = read_size(size, file, f"{where}{key}", "[W, H]")
        return h, w
    w_key, w = _get(entry, "width")
    h_key, h = _get(entry, "height")
    if w is None and h is None:
        return None
    if w is None or h is None:
        raise SceneError(f"{file}: {where}width/height: give both or neither")
    return read_int(h, file, f"{where}{h_key}"), read_int(w, file, f"{where}{w_key}")


@register_scene("opencv", keys=(*CAPTURE_KEYS, "calibration", "holdout"))
def load_opencv(cfg) -> Scene:
    """Load cameras calibrated with OpenCV (K, dist, R|rvec, t) and their images as a Scene."""
    root = resolve_root(option(cfg, "root"))
    cameras, top, path = _camera_list(root, option(cfg, "calibration", None))
    folder = path.parent if path.is_file() else path
    data_folder = root if root.is_dir() else root.parent
    frame = read_int(option(cfg, "frame", 0), "config", "scene.frame", 0)
    names, images, Ks, w2cs, sources = [], [], [], [], []
    for name, entry, file, where in cameras:
        if name in names:
            raise SceneError(f"{file}: {where}name: camera '{name}' appears twice")
        key, K = _get(entry, "K")
        K = check_intrinsics(K, file, f"{where}{key}")
        key, dist = _get(entry, "dist")
        dist = distortion(dist, file, f"{where}{key}")
        w2c = _pose(entry, file, where)
        if entry.get("image") is not None:
            image, source = read_path_frame(folder, read_text(entry["image"], file, f"{where}image"), frame)
        else:
            image, source = read_camera_frame(data_folder, name, frame)
        size = _expected_size(entry, file, where)
        if size is not None:
            check_image_size(image, size[0], size[1], source, file, f"{where}width/height")
        images.append(undistort(image, K, dist))
        Ks.append(K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]))
        w2cs.append(w2c)
        names.append(name)
        sources.append(source)
    file_box = box_from_value(top["bbox"], path, "bbox") if "bbox" in top else None
    given = option(cfg, "holdout", None)
    holdout = (read_names(given, "config", "scene.holdout") if given  # else the file's
               else read_names(top.get("holdout"), path, "holdout"))
    return make_scene(cfg, path, "opencv", names, images, Ks, w2cs, sources, file_box, holdout, frame,
                      file_conventions(top, path))
