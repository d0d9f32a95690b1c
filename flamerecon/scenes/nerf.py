"""NeRF / instant-ngp / nerfstudio ``transforms.json`` captures.

Top level (each may be overridden per frame): ``camera_angle_x`` (and ``camera_angle_y``) or
``fl_x`` / ``fl_y`` / ``cx`` / ``cy``, ``w`` / ``h``, distortion ``k1 k2 p1 p2`` (``k3``);
``frames``: list of ``file_path`` (relative to the json; may omit ``.png``, or name a video or a
frame folder, read at ``scene.frame``) and ``transform_matrix`` (camera->world, OpenGL axes).
Optional ``bbox`` = [[xmin, ymin, zmin], [xmax, ymax, zmax]] gives the box.

``cx``/``cy`` follow instant-ngp and nerfstudio (pixel centres at +0.5, as here), so they are
used unchanged; without them the principal point is the image centre (W/2, H/2).
Images are undistorted when distortion coefficients are given.

Config (``scene`` node): ``root`` (folder or the json), ``file`` (default transforms.json),
``frame``, ``downscale``, ``channels``, ``gamma``, ``black_level``, ``bbox``, ``holdout`` (view
names held out by default), ``silhouette``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from flamerecon.geometry.cameras import opengl_c2w_to_opencv_w2c
from flamerecon.scenes import register_scene
from flamerecon.scenes.base import Scene, SceneError
from flamerecon.scenes.calibration import (
    CAPTURE_KEYS,
    box_from_value,
    check_image_size,
    check_rigid,
    file_conventions,
    make_scene,
    option,
    read_json_object,
    resolve_root,
    undistort,
)
from flamerecon.scenes.frames import read_path_frame
from flamerecon.scenes.values import (
    FIELD_OF_VIEW,
    POSITIVE,
    read_float,
    read_int,
    read_names,
    read_text,
)

_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")


def _intrinsics(params: dict, width: int, height: int, path, where: str) -> np.ndarray:
    """K (pixel centres at +0.5) from fl_x/fl_y/cx/cy or camera_angle_x/y."""
    if "fl_x" in params:
        fx = read_float(params["fl_x"], path, f"{where}fl_x", POSITIVE)
    elif "camera_angle_x" in params:
        angle = read_float(params["camera_angle_x"], path, f"{where}camera_angle_x", FIELD_OF_VIEW)
        fx = 0.5 * width / math.tan(0.5 * angle)
    else:
        raise SceneError(f"{path}: {where}camera_angle_x: missing (and no fl_x)")
    if "fl_y" in params:
        fy = read_float(params["fl_y"], path, f"{where}fl_y", POSITIVE)
    elif "camera_angle_y" in params:
        angle = read_float(params["camera_angle_y"], path, f"{where}camera_angle_y", FIELD_OF_VIEW)
        fy = 0.5 * height / math.tan(0.5 * angle)
    else:
        fy = fx
    cx = read_float(params.get("cx", 0.5 * width), path, f"{where}cx")
    cy = read_float(params.get("cy", 0.5 * height), path, f"{where}cy")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _view_names(paths: list[str]) -> list[str]:
    """Short unique names: file stems, or the relative paths without extension when stems clash."""
    stems = [Path(p).stem if Path(p).suffix else Path(p).name for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [str(Path(p).with_suffix("")).lstrip("./") for p in paths]


def _duplicate(path, where: str, file_path: str, first: int, source=None, what: str = "") -> str:
    """The message for a frame that repeats an earlier one (a held-out copy would leak)."""
    same = what or (f"the image {source}" if source is not None else f"'{file_path}'")
    return (f"{path}: {where}file_path: '{file_path}' is a duplicate: {same} is already "
            f"frames[{first}]; list each view once (a held-out view's copy would be fitted)")


@register_scene("nerf", keys=(*CAPTURE_KEYS, "file", "holdout"))
def load_nerf(cfg) -> Scene:
    """Load a ``transforms.json`` capture as a Scene (views in file order)."""
    root = resolve_root(option(cfg, "root"))
    data, path = read_json_object(root, str(option(cfg, "file", "transforms.json")), "frames")
    if not isinstance(data.get("frames"), list) or not data["frames"]:
        raise SceneError(f"{path}: frames: missing or empty")
    folder = path.parent
    frame = read_int(option(cfg, "frame", 0), "config", "scene.frame", 0)
    images, Ks, w2cs, sources, file_paths = [], [], [], [], []
    seen: dict[str, int] = {}  # normalized file_path -> first frame index
    for i, entry in enumerate(data["frames"]):
        where = f"frames[{i}]."
        if not isinstance(entry, dict):
            raise SceneError(f"{path}: frames[{i}]: must be an object")
        file_path = read_text(entry.get("file_path"), path, f"{where}file_path")
        key = os.path.normpath(file_path)
        if key in seen:
            raise SceneError(_duplicate(path, where, file_path, seen[key]))
        seen[key] = i
        params = {**{k: v for k, v in data.items() if k != "frames"}, **entry}
        c2w = check_rigid(entry.get("transform_matrix"), path, f"{where}transform_matrix")
        image, source = read_path_frame(folder, file_path, frame)
        same = [k for k, earlier in enumerate(sources) if Path(earlier).resolve() == Path(source).resolve()]
        if same:
            raise SceneError(_duplicate(path, where, file_path, same[0], source))
        H, W = image.shape[:2]
        if "w" in params or "h" in params:
            h = read_int(params.get("h", H), path, f"{where}h")
            w = read_int(params.get("w", W), path, f"{where}w")
            check_image_size(image, h, w, source, path, f"{where}w/h")
        K = _intrinsics(params, W, H, path, where)
        dist = np.array([read_float(params.get(k, 0.0), path, f"{where}{k}") for k in _DISTORTION_KEYS])
        K_opencv = K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
        images.append(undistort(image, K_opencv, dist))
        Ks.append(K)
        w2cs.append(opengl_c2w_to_opencv_w2c(torch.from_numpy(c2w)).double().numpy())
        sources.append(source)
        file_paths.append(file_path)
    names = _view_names(file_paths)
    for i, name in enumerate(names):
        if names.index(name) != i:
            raise SceneError(_duplicate(path, f"frames[{i}].", file_paths[i], names.index(name),
                                        what=f"view name '{name}'"))
    file_box = box_from_value(data["bbox"], path, "bbox") if "bbox" in data else None
    holdout = read_names(option(cfg, "holdout", []), "config", "scene.holdout")
    return make_scene(cfg, path, "nerf", names, images, Ks, w2cs, sources, file_box, holdout, frame,
                      file_conventions(data, path))
