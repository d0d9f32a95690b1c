"""Converters from other calibration formats into an OpenCV calibration file that
``scene=opencv`` loads (:mod:`flamerecon.scenes.opencv_calib`; docs/own_capture.md):

- PINF / HyFluid ``info.json`` (:mod:`flamerecon.scenes.pinf`): camera_angle_x, camera_hw and the
  OpenGL camera->world ``transform_matrix`` per camera, the box from ``voxel_matrix`` and
  ``voxel_scale``, ``test_videos`` as the held-out cameras;
- COLMAP's text model (``cameras.txt``, ``images.txt``): intrinsics by camera model (pinhole and
  OpenCV-style radial/tangential distortion), world->camera quaternion and translation per image;
- MATLAB's ``cameraParameters`` / ``stereoParameters`` (:mod:`flamerecon.scenes.matlab`), both
  of its conventions.

Each converter returns a :class:`Conversion`: the record written as plain YAML (``cameras``:
name, K, dist, R, t with x_cam = R x_world + t, width, height, image relative to the file; and
``bbox`` / ``holdout`` / ``unit`` (metres per world unit) / ``up`` where known), the files it
read, and the frames to link beside the file where a pattern mapped a flat folder's files onto
cameras and frames (NAME/NNNNNN.png, links to them). K follows OpenCV's pixel convention (pixel
index k at coordinate k); COLMAP's (pixel centres at k + 0.5), MATLAB's (at k + 1) and PINF's
principal points are shifted to it here, and the loader shifts to flamerecon's (k + 0.5).
Every bad value is refused with one line naming the file, the line or field, and what to do.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from flamerecon.outputs.atomic import atomic_write_text
from flamerecon.scenes.base import SceneError
from flamerecon.scenes.calibration import check_rigid, read_json_object
from flamerecon.scenes.frames import read_path_frame
from flamerecon.scenes.image_pattern import ImagePattern, Images, camera_images, first_file
from flamerecon.scenes.matlab import CONVENTIONS, read_matlab_cameras
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
#: the file suffixes the converters write (YAML) and the loader finds by default
OUTPUT_SUFFIXES = (".yaml", ".yml")
#: how far from 1 a COLMAP quaternion's norm may be (rounding in the text), else refused
QUATERNION_NORM_TOLERANCE = 1e-3


@dataclass
class Conversion:
    """What a converter made: the ``record`` to write, the ``inputs`` it read (the output may
    be none of them), the frames to link beside the output per camera ({name: {frame: file}}),
    and lines that say how it read the input."""

    record: dict
    inputs: list[Path]
    links: dict[str, dict[int, Path]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    world_units: str | None = None  # a length the input names its world unit by (MATLAB's WorldUnits)


def _relative(target: Path, start: Path) -> str:
    return Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()


def _camera(name: str, K: np.ndarray, w2c: np.ndarray, width: int, height: int, image: str,
            dist: list[float] | None = None) -> dict:
    entry = {"name": name, "K": (np.asarray(K, float).round(10) + 0.0).tolist(),  # + 0.0: no -0.0
             "R": (w2c[:3, :3].round(12) + 0.0).tolist(), "t": (w2c[:3, 3].round(12) + 0.0).tolist(),
             "width": int(width), "height": int(height), "image": image}
    if dist and any(dist):
        entry["dist"] = [float(d) for d in dist]
    return entry


def _image_entry(name: str, images: Images, out: Path, links: dict) -> str:
    """The ``image`` field of a camera: its file relative to ``out``, or, for frames found by
    a pattern, the folder NAME beside ``out`` that will hold links to them (noted in ``links``)."""
    if isinstance(images, Path):
        return _relative(images, out.parent)
    links[name] = images
    return name


def pinf_to_opencv(info: str | os.PathLike, out: str | os.PathLike) -> Conversion:
    """The OpenCV calibration of a PINF/HyFluid capture (``info``: its info.json or folder),
    each camera's ``image`` its video (or frame folder) relative to ``out``."""
    data, path = read_json_object(Path(info), "info.json", "train_videos / test_videos")
    out = Path(out)
    cameras, holdout, names = [], [], {}
    for where, entry, held in _camera_entries(data, path):
        if not isinstance(entry, dict):
            raise SceneError(f"{path}: {where}: must be an object")
        file_name = read_text(entry.get("file_name"), path, f"{where}.file_name")
        name = Path(file_name).stem
        if name in names:
            raise SceneError(f"{path}: {where}.file_name: camera '{name}' appears twice (also {names[name]}); "
                             "keep one")
        names[name] = where
        H, W = read_size(entry.get("camera_hw"), path, f"{where}.camera_hw", "[H, W]")
        angle = read_float(entry.get("camera_angle_x"), path, f"{where}.camera_angle_x", FIELD_OF_VIEW)
        c2w = check_rigid(entry.get("transform_matrix"), path, f"{where}.transform_matrix")
        focal = 0.5 * W / math.tan(0.5 * angle)
        K = np.array([[focal, 0.0, 0.5 * W], [0.0, focal, 0.5 * H], [0.0, 0.0, 1.0]])  # OpenCV's pixel convention
        w2c = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))  # as opengl_c2w_to_opencv_w2c, in float64
        video = path.parent / file_name
        image = video if video.exists() or not video.with_suffix("").is_dir() else video.with_suffix("")
        cameras.append(_camera(name, K, w2c, W, H, _relative(image, out.parent)))
        if held:
            holdout.append(name)
    record: dict = {"cameras": cameras}
    box = pinf_box(data, path)
    if box is not None:
        record["bbox"] = [list(box[0]), list(box[1])]
    if holdout:
        record["holdout"] = holdout
    return Conversion(record, [path])


def _colmap_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of a COLMAP text file, comments and blank lines left out."""
    if not path.is_file():
        raise SceneError(f"{path}: not found (COLMAP's text model: cameras.txt and images.txt; "
                         "colmap model_converter --output_type TXT writes them from a binary model)")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise SceneError(f"{path}: cannot be read as text ({err}); is it COLMAP's binary model? "
                         "colmap model_converter --output_type TXT") from None
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def _numbers(fields: list[str], path: Path, line: int, what: str) -> list[float]:
    """``fields`` as finite numbers, else the line's error naming ``what`` they are."""
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise SceneError(f"{path}: line {line}: {what}: expected numbers, got {' '.join(fields)}") from None
    if not all(math.isfinite(v) for v in values):
        raise SceneError(f"{path}: line {line}: {what}: holds NaN or Inf ({' '.join(fields)})")
    return values


def _integer(text: str, path: Path, line: int, what: str, least: int = 0) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < least:
        raise SceneError(f"{path}: line {line}: {what}: expected an integer >= {least}, got {text}")
    return value


def read_colmap_cameras(path: Path) -> dict[str, tuple[np.ndarray, list[float], int, int]]:
    """COLMAP's ``cameras.txt``: {camera id: (K in OpenCV's pixel convention, OpenCV
    distortion, width, height)}; a CAMERA_ID defined twice is refused."""
    cameras, lines = {}, {}
    for line, text in _colmap_lines(path):
        fields = text.split()
        if len(fields) < 4:
            raise SceneError(f"{path}: line {line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id, model = str(_integer(fields[0], path, line, "CAMERA_ID")), fields[1]
        if camera_id in cameras:
            raise SceneError(f"{path}: line {line}: CAMERA_ID {camera_id} is defined twice (lines {lines[camera_id]} "
                             f"and {line}); keep one")
        if model not in COLMAP_MODELS:
            raise SceneError(f"{path}: line {line}: camera model {model} is not supported; use one of "
                             f"{sorted(COLMAP_MODELS)} (colmap image_undistorter makes PINHOLE images)")
        names, distortion = COLMAP_MODELS[model]
        width, height = (_integer(f, path, line, what, 1) for f, what in zip(fields[2:4], ("WIDTH", "HEIGHT")))
        params = _numbers(fields[4:], path, line, "PARAMS")
        if len(params) != len(names):
            raise SceneError(f"{path}: line {line}: {model} takes {len(names)} parameters "
                             f"({' '.join(names)}), got {len(params)}")
        p = dict(zip(names, params))
        fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
        if fx <= 0 or fy <= 0:
            raise SceneError(f"{path}: line {line}: focal lengths must be positive, got {fx:g}, {fy:g}")
        K = np.array([[fx, 0.0, p["cx"] - 0.5], [0.0, fy, p["cy"] - 0.5], [0.0, 0.0, 1.0]])
        # OpenCV's order k1 k2 p1 p2 [k3 k4 k5 k6], the terms a model lacks 0
        dist = ([p.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")] + [p[k] for k in ("k3", "k4", "k5", "k6") if k in p]
                if distortion else [])
        cameras[camera_id], lines[camera_id] = (K, dist, width, height), line
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


def _is_points_line(fields: list[str]) -> bool:
    """Whether a line is an image's POINTS2D line (X Y POINT3D_ID triples)."""
    if len(fields) % 3:
        return False
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def read_colmap_images(path: Path) -> list[tuple[int, str, np.ndarray, str]]:
    """COLMAP's ``images.txt``: (line, NAME, world->camera 4x4, CAMERA_ID) per image. The NAME
    is the rest of its line (spaces kept); a line that is neither an image line nor a POINTS2D
    line, a zero, non-finite or non-unit quaternion, and an IMAGE_ID given twice are refused."""
    images, ids = [], {}
    for line, text in _colmap_lines(path):
        fields = text.split()
        if _is_points_line(fields):
            continue
        if len(fields) < 10:
            raise SceneError(f"{path}: line {line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, or the "
                             f"image's POINTS2D line (X Y POINT3D_ID ...), got {len(fields)} fields")
        fields = text.split(maxsplit=9)  # NAME: the rest of the line
        image_id = _integer(fields[0], path, line, "IMAGE_ID")
        if image_id in ids:
            raise SceneError(f"{path}: line {line}: IMAGE_ID {image_id} is defined twice (lines {ids[image_id]} and "
                             f"{line}); keep one")
        ids[image_id] = line
        qw, qx, qy, qz, tx, ty, tz = _numbers(fields[1:8], path, line, "QW QX QY QZ TX TY TZ")
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise SceneError(f"{path}: line {line}: QW QX QY QZ: " + ("a zero quaternion is no rotation" if norm == 0
                             else f"not a unit quaternion (norm {norm:.6g})") + "; COLMAP writes unit quaternions "
                             "(is the line IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME?)")
        camera_id = str(_integer(fields[8], path, line, "CAMERA_ID"))
        w2c = np.eye(4)
        w2c[:3, :3] = quaternion_matrix(qw, qx, qy, qz)
        w2c[:3, 3] = [tx, ty, tz]
        images.append((line, fields[9], w2c, camera_id))
    if not images:
        raise SceneError(f"{path}: no image pose line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
    return images


def colmap_to_opencv(model: str | os.PathLike, images: str | os.PathLike, out: str | os.PathLike,
                     pattern: ImagePattern | None = None) -> Conversion:
    """The OpenCV calibration of a COLMAP text model (``model``: the folder of cameras.txt and
    images.txt): one camera per image, named by the image's file stem (by the pattern's
    ``{camera}`` where its NAME fits ``pattern``, whose files in ``images`` are then that
    camera's frames); its ``image`` the file in ``images`` relative to ``out``."""
    model, folder, out = Path(model), Path(images), Path(out)
    intrinsics = read_colmap_cameras(model / "cameras.txt")
    path = model / "images.txt"
    poses, names = [], {}
    for line, image_name, w2c, camera_id in read_colmap_images(path):
        if camera_id not in intrinsics:
            raise SceneError(f"{path}: line {line}: CAMERA_ID {camera_id} is not in {model / 'cameras.txt'}")
        hit = pattern.match(Path(image_name).name) if pattern is not None else None
        name = hit[0] if hit is not None else Path(image_name).stem
        if name in names:
            raise SceneError(f"{path}: line {line}: camera name {name!r} (the image's "
                             f"{'camera by --pattern' if hit else 'stem'}) appears twice (also line {names[name]})")
        names[name] = line
        poses.append((name, image_name, w2c, intrinsics[camera_id]))
    if pattern is not None:
        found = camera_images(list(names), folder, pattern)
    else:
        found = {}
        for name, image_name, *_ in poses:
            found[name] = folder / image_name
            if not found[name].exists():
                raise SceneError(f"{path}: line {names[name]}: image {image_name!r} not found in {folder}; give the "
                                 "images folder with --images (or name its files with --pattern)")
    conversion = Conversion({}, [model / "cameras.txt", path])
    cameras = []
    for name, _, w2c, (K, dist, width, height) in poses:
        image = _image_entry(name, found[name], out, conversion.links)
        cameras.append(_camera(name, K, w2c, width, height, image, dist))
    conversion.record["cameras"] = cameras
    return conversion


def matlab_to_opencv(file: str | os.PathLike, images: str | os.PathLike, out: str | os.PathLike,
                     pattern: ImagePattern | None = None) -> Conversion:
    """The OpenCV calibration of a MATLAB calibration (:mod:`flamerecon.scenes.matlab`), its
    cameras' images in ``images`` (by ``pattern``, else named after each camera); each camera's
    ``ImageSize`` [rows, cols] is checked against its first image."""
    file, folder, out = Path(file), Path(images), Path(out)
    cameras, what = read_matlab_cameras(file)
    found = camera_images([c.name for c in cameras], folder, pattern)
    conversion = Conversion({}, [file])
    entries = []
    for cam in cameras:
        first = first_file(found[cam.name])
        image, _ = read_path_frame(first.parent, first.name, 0)
        H, W = image.shape[:2]
        if cam.size is not None and cam.size != (H, W):
            hint = (" (MATLAB's ImageSize is [rows, cols]: this one is [cols, rows])" if cam.size == (W, H)
                    else "")
            raise SceneError(f"{file}: {cam.name}: ImageSize is {list(cam.size)} but {first} is {H} rows x {W} "
                             f"columns{hint}")
        entries.append(_camera(cam.name, cam.K, cam.w2c, W, H, _image_entry(cam.name, found[cam.name], out,
                                                                                conversion.links), cam.dist))
    conversion.record["cameras"] = entries
    conversion.notes = [f"{file}: {what}; {convention}" for convention in _conventions(cameras)]
    units = {c.world_units for c in cameras if c.world_units}
    conversion.world_units = units.pop() if len(units) == 1 else None
    return conversion


def _conventions(cameras) -> list[str]:
    """One line per set of cameras read in the same conventions."""
    groups: dict[tuple[str, str], list[str]] = {}
    for cam in cameras:
        groups.setdefault((cam.intrinsics_convention, cam.pose_convention), []).append(cam.name)
    lines = []
    for (intrinsics, pose), names in groups.items():
        said = CONVENTIONS.get(intrinsics, intrinsics)
        if pose != intrinsics:
            said = f"intrinsics {said}; pose {CONVENTIONS.get(pose, pose).split(': ', 1)[-1]}"
        lines.append(f"MATLAB {said} ({', '.join(names) if len(groups) > 1 else 'every camera'}); "
                     "principal point 1-based, moved by -1 px")
    return lines


def check_output(path: Path, conversion: Conversion, force: bool) -> None:
    """Refuse, before anything is written, an output that is one of the converter's inputs (an
    input file or image, even with ``force``), an existing file without ``force``, or a frame
    folder NAME beside it that holds anything but links (links are replaced with ``force``)."""
    target = path.resolve()
    used = [*conversion.inputs, *(f for frames in conversion.links.values() for f in frames.values())]
    used += [path.parent / c["image"] for c in conversion.record["cameras"] if c["name"] not in conversion.links]
    for source in used:
        if Path(source).resolve() == target:
            raise SceneError(f"{path}: is the converter's own input ({source}); write the calibration elsewhere, "
                             "e.g. OUT/calibration.yaml")
    if path.suffix.lower() not in OUTPUT_SUFFIXES:
        raise SceneError(f"{path}: the converter writes YAML; name the file .yaml or .yml (e.g. OUT/calibration.yaml)")
    if path.exists() and not force:
        raise SceneError(f"{path}: exists; give --force to replace it, or another file name")
    for name in conversion.links:
        folder = path.parent / name
        if folder.exists() and not (force and folder.is_dir() and all(p.is_symlink() for p in folder.iterdir())):
            raise SceneError(f"{folder}: exists; the frames of camera '{name}' are linked there: "
                             + ("it holds files that are not links; move it away" if force else
                                "give --force to replace its links, or write into another folder"))


def write_conversion(path: str | os.PathLike, conversion: Conversion, source: str) -> Path:
    """Write a checked conversion (:func:`check_output`): the frame folders of links first
    (each made whole in a temporary folder, then renamed into place), the YAML last."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for name, frames in conversion.links.items():
        staging = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=path.parent))
        try:
            os.chmod(staging, _folder_mode())  # mkdtemp makes 0700
            for frame, file in sorted(frames.items()):
                link = staging / f"{frame:06d}{file.suffix.lower()}"
                os.symlink(os.path.relpath(file.resolve(), path.parent.resolve() / name), link)
            folder = path.parent / name
            if folder.exists():
                shutil.rmtree(folder)
            os.replace(staging, folder)
        finally:
            if staging.exists():
                shutil.rmtree(staging)
    return write_calibration(path, conversion.record, source)


def _folder_mode() -> int:
    """The permissions of a new folder under this process's umask (read by setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o777 & ~mask


def write_calibration(path: str | os.PathLike, record: dict, source: str) -> Path:
    """Write a converted calibration as YAML (whole or not at all), a comment naming ``source``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    head = (f"# converted from {source} by flamerecon (scripts/convert_capture.py); OpenCV conventions:\n"
            "# x_cam = R x_world + t, K with pixel index k at coordinate k; image: relative to this file\n")
    atomic_write_text(path, head + yaml.safe_dump(record, sort_keys=False, default_flow_style=None, width=100))
    return path
