"""What every calibrated-capture loader shares: checking calibration values, finding the data
folder, turning per-camera images and intrinsics into a Scene's batch (downscaled, linearized,
one channel count), and choosing the box.

Every check raises :class:`SceneError` with one line that names the file and the field.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import torch

from flamerecon.errors import ConfigError
from flamerecon.geometry.axes import UP_AXES, axis_name, up_from_cameras
from flamerecon.geometry.cameras import make_cameras
from flamerecon.geometry.photometry import linearize
from flamerecon.geometry.silhouettes import estimate_bbox, silhouettes
from flamerecon.plain import json_value
from flamerecon.resources import checkout_root
from flamerecon.scenes.base import Scene, SceneError
from flamerecon.scenes.frames import is_link_loop
from flamerecon.scenes.values import POSITIVE, read_array, read_float, read_int, read_matrix

#: a capture's conventions: its up axis, metres per world unit and frames per second, each read
#: from the ``scene`` config, else the calibration file's top level (:func:`conventions`)
CONVENTION_KEYS = ("up", "unit", "frame_rate")

#: the ``scene`` options every capture loader reads (each adds its own).
CAPTURE_KEYS = ("root", "frame", "downscale", "channels", "gamma", "black_level", "bbox", "silhouette",
                *CONVENTION_KEYS)


def option(cfg, key: str, default=None):
    """``cfg[key]`` for a dict or OmegaConf node, ``default`` when absent or null."""
    value = cfg.get(key, default)
    return default if value is None else value


def resolve_root(root, field: str = "scene.root") -> Path:
    """The data folder (or file) named by ``root``.

    An absolute path is taken as is. A relative one is tried against the working directory
    (the run layer, :func:`flamerecon.run.runner.anchor_scene_root`, has already made absolute a
    root found under the folder the command was started in), then against the repository root
    when the package runs from a checkout.
    """
    if root is None or str(root) == "":
        raise SceneError(f"config: {field}: no data folder given")
    path = Path(os.path.expanduser(str(root)))
    if path.is_absolute():
        candidates = [path]
    else:
        checkout = checkout_root()
        candidates = [Path.cwd() / path] + ([checkout / path] if checkout is not None else [])
    for candidate in candidates:
        if candidate.exists():
            return candidate.resolve()
        if is_link_loop(candidate):
            raise SceneError(f"config: {field}: '{root}' is a symbolic link loop ({candidate} leads back "
                             "to itself); point it at the data folder")
    tried = ", ".join(str(c) for c in dict.fromkeys(candidates))
    raise SceneError(f"config: {field}: '{root}' does not exist (tried {tried})")


def read_json_object(root: Path, file_name: str, expected: str) -> tuple[dict, Path]:
    """The JSON object in ``root/file_name`` (or in ``root`` when it is a file) and its path;
    ``expected`` says what its top level must hold, for the error message."""
    path = root / file_name if root.is_dir() else root
    if not path.is_file():
        raise SceneError(f"{path}: {file_name} not found")
    try:
        data = json_value(path.read_text())
    except (ValueError, OSError) as err:
        raise SceneError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: top level must be an object with {expected}")
    return data, path


def check_intrinsics(K: np.ndarray, file, field: str) -> np.ndarray:
    """A 3x3 pinhole K with positive focal lengths and last row (0, 0, 1)."""
    K = read_matrix(K, (3, 3), file, field)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SceneError(
            f"{file}: {field}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}"
        )
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise SceneError(
            f"{file}: {field}: not an intrinsics matrix (rows 2-3 must be [0 fy cy], [0 0 1])"
        )
    return K


def check_rotation(
    R: np.ndarray, file, field: str, tol: float = 1e-3, proper: bool = True
) -> np.ndarray:
    """An orthonormal 3x3 (R R^T = I within ``tol``), with det R = +1 when ``proper``."""
    R = read_matrix(R, (3, 3), file, field)
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > tol:
        raise SceneError(f"{file}: {field}: rotation is not orthonormal (|R R^T - I| = {err:.2g})")
    if proper and np.linalg.det(R) < 0:
        raise SceneError(f"{file}: {field}: rotation has determinant -1 (a reflection)")
    return R


def check_rigid(T: np.ndarray, file, field: str, proper: bool = True) -> np.ndarray:
    """A 4x4 rigid transform: orthonormal rotation block, last row (0, 0, 0, 1)."""
    T = read_matrix(T, (4, 4), file, field)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise SceneError(f"{file}: {field}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    check_rotation(T[:3, :3], file, field, proper=proper)
    return T


def check_image_size(
    image: np.ndarray, height: int, width: int, image_file, calib_file, field: str
):
    """SceneError when an image's size disagrees with its calibration's (integers, as
    :func:`~flamerecon.scenes.values.read_int` gives them)."""
    h, w = image.shape[:2]
    if (h, w) != (height, width):
        from flamerecon.scenes.orientation import TURNS, exif_orientation

        turn = exif_orientation(image_file) if image_file is not None else 1
        if turn in (5, 6, 7, 8) and (w, h) == (height, width):
            raise SceneError(
                f"{image_file}: image is {w}x{h} (WxH) as displayed, its EXIF orientation {turn} ({TURNS[turn]}) "
                f"applied, but {calib_file}: {field} says {width}x{height}, the size as stored: calibrate on the "
                "images as displayed, or store them upright (exiftool -Orientation=1 -n FILE)")
        raise SceneError(
            f"{image_file}: image is {w}x{h} (WxH) but {calib_file}: {field} says {width}x{height}"
        )


def downscale_factor(cfg) -> int:
    """``scene.downscale`` as a positive int (1 = native resolution)."""
    return read_int(option(cfg, "downscale", 1), "config", "scene.downscale")


def downscale_view(image: np.ndarray, K: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Shrink an image (H, W, C) by area averaging and scale K (pixel centres at +0.5) to match.

    With centres at +0.5 a continuous pixel coordinate scales exactly by the size ratio, so
    fx, cx scale by W'/W and fy, cy by H'/H (H' = H // factor).
    """
    if factor == 1:
        return image, K
    H, W = image.shape[:2]
    h, w = H // factor, W // factor
    if h < 1 or w < 1:
        raise SceneError(f"config: scene.downscale: {factor} leaves no pixels of a {W}x{H} image")
    small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    if small.ndim == 2:
        small = small[:, :, None]
    S = np.diag([w / W, h / H, 1.0])
    return small, S @ K


def to_channels(images: list[np.ndarray], channels) -> list[np.ndarray]:
    """Give every image (H, W, C) the same channel count: ``channels`` = 1, 3 or ``"auto"``.

    ``auto`` keeps one channel when every image is grayscale (one channel, or three equal within
    3/255, as videos of gray scenes decode), three otherwise.
    """
    if channels == "auto":
        gray = all(
            im.shape[2] == 1 or float(np.abs(im - im.mean(2, keepdims=True)).max()) <= 3 / 255
            for im in images
        )
        channels = 1 if gray else 3
    if channels not in (1, 3):
        raise SceneError(f"config: scene.channels: must be 1, 3 or 'auto', got {channels!r}")
    out = []
    for im in images:
        if im.shape[2] == channels:
            out.append(im)
        elif channels == 3:
            out.append(np.repeat(im, 3, axis=2))
        else:
            luma = im @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
            out.append(luma[:, :, None])
    return out


def stack_views(images: list[np.ndarray], sources: list) -> torch.Tensor:
    """Per-view images (H, W, C) of one size -> (B, C, H, W) float32."""
    sizes = {im.shape for im in images}
    if len(sizes) > 1:
        listing = ", ".join(f"{s}: {im.shape[1]}x{im.shape[0]}" for s, im in zip(sources, images))
        raise SceneError(
            f"images: views differ in size after loading ({listing}); flamerecon needs one size"
        )
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous().float()


def build_views(
    cfg,
    names: list[str],
    images: list[np.ndarray],
    Ks: list[np.ndarray],
    w2cs: list[np.ndarray],
    sources: list,
):
    """Downscale, unify channels, linearize, and build the camera batch.

    ``images``: per view (H, W, C) float32 in [0, 1] at native size; ``Ks``: per view 3x3 with
    pixel centres at +0.5; ``w2cs``: per view OpenCV world->camera 4x4. Returns
    (cameras, linear images (B, C, H, W), the recorded images or None when they are the same).
    """
    factor = downscale_factor(cfg)
    small, Ks_small = [], []
    for im, K in zip(images, Ks):
        s, k = downscale_view(im, K, factor)
        small.append(s)
        Ks_small.append(k)
    small = to_channels(small, option(cfg, "channels", "auto"))
    recorded = stack_views(small, sources)
    black_level = read_float(option(cfg, "black_level", 0.0), "config", "scene.black_level")
    try:
        batch = linearize(recorded, option(cfg, "gamma", 1.0), black_level)
    except ValueError as err:
        raise SceneError(f"config: {err}") from None
    H, W = batch.shape[-2:]
    cams = make_cameras(
        torch.from_numpy(np.stack(Ks_small)).float(),
        torch.from_numpy(np.stack(w2cs)).float(),
        torch.full((len(names),), H),
        torch.full((len(names),), W),
    )
    return cams, batch, (None if batch is recorded else recorded)


def box_from_config(cfg, field: str = "scene.bbox"):
    """``scene.bbox`` = [[xmin, ymin, zmin], [xmax, ymax, zmax]] or None when unset."""
    value = option(cfg, "bbox", None)
    if value is None:
        return None
    return box_from_value(value, "config", field)


def box_from_value(value, file, field: str):
    """A [[min xyz], [max xyz]] value checked: finite, min < max on every axis."""
    box = read_matrix(value, (2, 3), file, field)
    if not (box[0] < box[1]).all():
        raise SceneError(
            f"{file}: {field}: min must be below max on every axis, got {box.tolist()}"
        )
    return tuple(box[0].tolist()), tuple(box[1].tolist())


def silhouette_options(cfg) -> dict:
    """Keyword arguments for :func:`~flamerecon.geometry.silhouettes.silhouettes` from the config."""
    node = option(cfg, "silhouette", {}) or {}
    keys = ("method", "threshold", "dilate_px", "blur_px", "speck_px", "close_px")
    return {k: node[k] for k in keys if k in node and node[k] is not None}


def choose_box(cfg, file_box, cams, images: torch.Tensor, source) -> tuple[tuple, tuple, str]:
    """The scene's box: ``scene.bbox`` from the config, else the file's, else estimated from the
    silhouette cones. Returns (bbox_min, bbox_max, where it came from)."""
    configured = box_from_config(cfg)
    if configured is not None:
        return configured[0], configured[1], "config scene.bbox"
    if file_box is not None:
        return file_box[0], file_box[1], f"{source}"
    try:
        masks = silhouettes(images, **silhouette_options(cfg), field="scene.silhouette")
        lo, hi = estimate_bbox(cams, masks)
    except ConfigError:
        raise
    except ValueError as err:
        raise SceneError(f"{source}: no box in the file or config, and {err}") from None
    return lo, hi, "silhouette cones"


def distortion(value, file, field: str) -> np.ndarray:
    """OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]) as a flat array."""
    d = read_array(value if value is not None else [], file, field).reshape(-1)
    if d.size not in (0, 4, 5, 8, 12, 14):
        raise SceneError(f"{file}: {field}: expected 4, 5, 8, 12 or 14 coefficients, got {d.size}")
    return d


def undistort(image: np.ndarray, K_opencv: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Remove lens distortion from an image (H, W, C), keeping the same K.

    ``K_opencv`` uses OpenCV's pixel convention (index k at coordinate k), as ``cv2.undistort``.
    """
    if dist.size == 0 or not np.any(dist):
        return image
    out = cv2.undistort(image, K_opencv, dist)
    return out[:, :, None] if out.ndim == 2 else out


def file_conventions(top: dict, file) -> dict:
    """The calibration file's top-level ``up`` (an axis name such as ``+z``), ``unit`` (metres
    per world unit) and ``frame_rate`` (frames per second), checked; absent ones left out."""
    found = {}
    if top.get("up") is not None:
        up = axis_name(top["up"])
        if up is None:
            raise SceneError(f"{file}: up: {top['up']!r} is not an axis; give one of {', '.join(UP_AXES)}")
        found["up"] = up
    for key in ("unit", "frame_rate"):
        if top.get(key) is not None:
            found[key] = read_float(top[key], file, key, POSITIVE)
    return found


def conventions(cfg, cams, given: dict, file) -> dict:
    """The Scene's ``up``, ``up_source``, ``unit`` and ``frame_rate``: each from the config
    (``scene.up`` other than ``auto``, ``scene.unit``, ``scene.frame_rate``), else from ``given``
    (the calibration file's, :func:`file_conventions`), else the up axis the cameras show
    upwards (:func:`~flamerecon.geometry.axes.up_from_cameras`; +y where they disagree) and an
    unknown unit and frame rate."""
    out = {"unit": given.get("unit"), "frame_rate": given.get("frame_rate")}
    for key in ("unit", "frame_rate"):
        if option(cfg, key) is not None:
            out[key] = read_float(option(cfg, key), "config", f"scene.{key}", POSITIVE)
    configured = option(cfg, "up", "auto")
    if configured != "auto":
        up = axis_name(configured)
        if up is None:
            raise SceneError(f"config: scene.up: {configured!r} is not an axis; give auto or one of "
                             f"{', '.join(UP_AXES)}")
        return {**out, "up": up, "up_source": "config scene.up"}
    if "up" in given:
        return {**out, "up": given["up"], "up_source": f"{file}: up"}
    up, angle = up_from_cameras(cams.extrinsics)
    if up is None:
        return {**out, "up": "+y", "up_source": f"the default: the cameras' image-up directions do not agree "
                                                f"on an axis ({angle:.0f} deg off the nearest); set scene.up"}
    return {**out, "up": up, "up_source": f"auto: the cameras' image-up direction, {angle:.0f} deg off {up} "
                                          "(scene.up or the calibration file's up if the flame rises otherwise)"}


def make_scene(
    cfg, path, default_name: str, names: list[str], images: list[np.ndarray], Ks, w2cs,
    sources: list, file_box, holdout: list[str], frame: int, file_values: dict | None = None, **meta,
) -> Scene:
    """The Scene every loader returns: views stacked and checked, the box chosen (config,
    file, or silhouettes), ``holdout`` checked against the view names, the conventions
    (:func:`conventions`) from the config, else ``file_values`` (the file's), else the cameras."""
    cams, batch, recorded = build_views(cfg, names, images, Ks, w2cs, sources)
    lo, hi, box_source = choose_box(cfg, file_box, cams, batch, path)
    unknown = [h for h in holdout if h not in names]
    if unknown:
        raise SceneError(f"{path}: holdout: views {unknown} are not among the cameras {names}")
    return Scene(
        name=str(option(cfg, "name", default_name)), views=names, cameras=cams, images=batch,
        bbox_min=lo, bbox_max=hi, default_holdout=list(holdout), source=str(path),
        meta={"frame": frame, "files": [str(s) for s in sources], "bbox_source": str(box_source),
              **meta},
        response=None if recorded is None else {
            "gamma": option(cfg, "gamma", 1.0), "black_level": read_float(option(cfg, "black_level", 0.0), "config",
                                                                          "scene.black_level")},
        recorded_images=recorded, **conventions(cfg, cams, file_values or {}, path),
    )
