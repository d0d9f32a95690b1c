"""PINF / HyFluid ``info.json`` captures (the ScalarFlow smoke of ``shared/data``).

``info.json`` lists cameras in ``train_videos`` and ``test_videos``; each has ``file_name``
(its video; frames may also sit in a folder of that name without ``.mp4``),
``transform_matrix`` (camera->world, OpenGL axes), ``camera_angle_x`` (horizontal field of
view, radians) and ``camera_hw`` = [H, W]. PINF's intrinsics: f = 0.5 W / tan(0.5 angle),
principal point (W/2, H/2) with pixel index k at coordinate k, so ours is (W/2 + 0.5, H/2 + 0.5).
The smoke box: PINF swaps columns 0 and 2 of ``voxel_matrix``; world = M (p * voxel_scale) for
p in [0, 1]^3; the scene keeps the axis-aligned box around those eight corners.

Config (``scene`` node): ``root`` (the folder or the info.json), ``frame``, ``downscale``,
``channels``, ``gamma``, ``black_level``, ``bbox`` (overrides the file's box), ``silhouette``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from flamerecon.geometry.cameras import opengl_c2w_to_opencv_w2c
from flamerecon.scenes import register_scene
from flamerecon.scenes.base import Scene, SceneError
from flamerecon.scenes.calibration import (
    CAPTURE_KEYS,
    check_image_size,
    check_rigid,
    file_conventions,
    make_scene,
    option,
    read_json_object,
    resolve_root,
)
from flamerecon.scenes.frames import read_camera_frame
from flamerecon.scenes.values import (
    FIELD_OF_VIEW,
    POSITIVE,
    read_float,
    read_int,
    read_matrix,
    read_size,
    read_text,
)


def pinf_box(info: dict, file) -> tuple[tuple, tuple] | None:
    """Axis-aligned world box of PINF's ``voxel_matrix`` / ``voxel_scale``, or None if absent."""
    if "voxel_matrix" not in info and "voxel_scale" not in info:
        return None
    # PINF's column swap makes the matrix a reflection, so only orthonormality is required
    M = check_rigid(info.get("voxel_matrix"), file, "voxel_matrix", proper=False)
    scale = read_matrix(info.get("voxel_scale"), (3,), file, "voxel_scale")
    if (scale <= 0).any():
        raise SceneError(f"{file}: voxel_scale: must be positive, got {scale.tolist()}")
    M = M[:, [2, 1, 0, 3]]  # PINF's column swap
    unit = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.float64)
    corners = (unit * scale) @ M[:3, :3].T + M[:3, 3]
    return tuple(corners.min(0).tolist()), tuple(corners.max(0).tolist())


def _camera_entries(info: dict, path: Path) -> list[tuple[str, dict, bool]]:
    """(field path, entry, held out) for every camera, in file order: train then test."""
    entries = []
    for key, held in (("train_videos", False), ("test_videos", True)):
        value = info.get(key, [])
        if not isinstance(value, list):
            raise SceneError(f"{path}: {key}: must be a list of cameras")
        entries += [(f"{key}[{i}]", entry, held) for i, entry in enumerate(value)]
    if not entries:
        raise SceneError(f"{path}: train_videos: missing or empty (no cameras)")
    return entries


@register_scene("scalarflow", keys=CAPTURE_KEYS)
@register_scene("pinf", keys=CAPTURE_KEYS)
def load_pinf(cfg) -> Scene:
    """Load one frame of a PINF/HyFluid capture as a Scene (views in file order)."""
    root = resolve_root(option(cfg, "root"))
    info, path = read_json_object(root, "info.json", "train_videos / test_videos")
    folder = path.parent
    frame = read_int(option(cfg, "frame", 0), "config", "scene.frame", 0)
    names, images, Ks, w2cs, sources, holdout, rates = [], [], [], [], [], [], set()
    for where, entry, held in _camera_entries(info, path):
        if not isinstance(entry, dict):
            raise SceneError(f"{path}: {where}: must be an object")
        file_name = read_text(entry.get("file_name"), path, f"{where}.file_name")
        name = Path(file_name).stem
        if name in names:
            raise SceneError(f"{path}: {where}.file_name: camera '{name}' appears twice")
        H, W = read_size(entry.get("camera_hw"), path, f"{where}.camera_hw", "[H, W]")
        angle = read_float(entry.get("camera_angle_x"), path, f"{where}.camera_angle_x", FIELD_OF_VIEW)
        c2w = check_rigid(entry.get("transform_matrix"), path, f"{where}.transform_matrix")
        frame_num = entry.get("frame_num")
        if frame_num is not None and not frame < read_int(frame_num, path, f"{where}.frame_num"):
            raise SceneError(
                f"{path}: {where}.frame_num: frame {frame} is outside its {frame_num} frames"
            )
        if entry.get("frame_rate") is not None:
            rates.add(read_float(entry["frame_rate"], path, f"{where}.frame_rate", POSITIVE))
            if len(rates) > 1:
                raise SceneError(f"{path}: {where}.frame_rate: the cameras run at {' and '.join(f'{r:g}' for r in sorted(rates))} "
                                 "frames per second, so one frame number is not one instant in every camera; "
                                 "resample the videos to one rate")
        image, source = read_camera_frame(folder, file_name, frame)
        check_image_size(image, H, W, source, path, f"{where}.camera_hw")
        f = 0.5 * W / math.tan(0.5 * angle)
        Ks.append(np.array([[f, 0.0, 0.5 * W + 0.5], [0.0, f, 0.5 * H + 0.5], [0.0, 0.0, 1.0]]))
        w2cs.append(opengl_c2w_to_opencv_w2c(torch.from_numpy(c2w)).double().numpy())
        names.append(name)
        images.append(image)
        sources.append(source)
        if held:
            holdout.append(name)
    return make_scene(
        cfg, path, "scalarflow", names, images, Ks, w2cs, sources, pinf_box(info, path), holdout,
        frame, **{k: read_float(info[k], path, k) for k in ("near", "far") if k in info},
        file_values={**file_conventions(info, path), **({"frame_rate": rates.pop()} if rates else {})},
    )
