"""MATLAB camera calibrations (Computer Vision Toolbox) in OpenCV's conventions, for
``scripts/convert_capture.py matlab`` (docs/own_capture.md, "MATLAB").

The file is a ``jsonencode``d value or a MAT-file (``save``, read with scipy.io; scipy reads
structs, not MATLAB objects: save ``toStruct(params)``). It holds one camera
(``cameraParameters`` or ``cameraIntrinsics``, named by the file's stem), a ``stereoParameters``
(``camera1``, ``camera2``; camera 1's frame is the world), a map from camera name to camera
(a struct, or a MAT-file's variables), or an array of cameras (``cam1``, ``cam2``, ...).
Each field is read in the convention it was written in, detected from its name:

- pre-R2022b: ``IntrinsicMatrix`` = K transposed ([fx 0 0; s fy 0; cx cy 1]); poses
  postmultiply, x_cam = x_world * R + t: ``RotationMatrix``/``TranslationVector`` (from
  ``extrinsics``), ``RotationMatrices``/``TranslationVectors`` (one pattern), a ``rigid3d``'s
  ``Rotation``/``Translation``, a stereo pair's ``RotationOfCamera2``/``TranslationOfCamera2``;
- R2022b and later: ``K``; poses premultiply, x_cam = R * x_world + t: a ``rigidtform3d``
  (``R`` and ``Translation``, or ``A``) as ``Extrinsics`` (from ``estimateExtrinsics``),
  ``PatternExtrinsics`` (one pattern) or a stereo pair's ``PoseCamera2``.

In both, pixel centres sit at whole numbers from 1 (OpenCV's from 0: cx and cy move by -1),
``ImageSize`` is [rows, cols], ``RadialDistortion`` [k1 k2 (k3)] and ``TangentialDistortion``
[p1 p2] are OpenCV's k1 k2 p1 p2 k3, and a rotation vector (``RotationVector(s)``) is OpenCV's
rvec. Where a file holds one quantity twice (K and IntrinsicMatrix, a pattern's rotation as
matrix and vector), both are read and must agree.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flamerecon.scenes.base import SceneError
from flamerecon.scenes.calibration import check_rotation
from flamerecon.scenes.values import read_array, read_matrix, read_size

PRE = "pre-R2022b"
POST = "R2022b+"
#: what each convention means, as the converter prints it
CONVENTIONS = {
    PRE: "pre-R2022b: IntrinsicMatrix = K', pose postmultiply x_cam = x_world*R + t",
    POST: "R2022b+: K, pose premultiply x_cam = R*x_world + t (rigidtform3d)",
}
#: fields that make a map a camera
_INTRINSIC_KEYS = ("K", "IntrinsicMatrix", "Intrinsics", "FocalLength")
#: metres per MATLAB ``WorldUnits`` label, for the converter's hint
WORLD_UNITS = {"mm": 1e-3, "millimeters": 1e-3, "millimetres": 1e-3, "cm": 1e-2, "centimeters": 1e-2,
               "m": 1.0, "meters": 1.0, "metres": 1.0, "in": 0.0254, "inches": 0.0254}
#: how far two readings of one quantity may differ (a file's own rounding)
_AGREE = 1e-6


@dataclass
class MatlabCamera:
    """One camera read from a MATLAB file, in OpenCV's conventions: ``K`` (3, 3) with pixel
    index k at coordinate k, ``dist`` (k1 k2 p1 p2 [k3]; empty: none), ``w2c`` (4, 4) world->
    camera, ``size`` (H, W) from ``ImageSize`` or None, and the conventions its intrinsics and
    its pose were written in (:data:`PRE`, :data:`POST`, or a word for one that is the same
    in both)."""

    name: str
    K: np.ndarray
    dist: list[float]
    w2c: np.ndarray
    size: tuple[int, int] | None
    intrinsics_convention: str
    pose_convention: str
    world_units: str | None


def read_matlab_file(path: Path):
    """The file's value as plain Python (dicts, lists, numbers, arrays): a JSON document (a
    key given twice in one object is refused), or a MAT-file's one variable (its variables as a
    map when it holds several)."""
    if not path.is_file():
        raise SceneError(f"{path}: not found (a jsonencode'd or saved MATLAB calibration)")
    with open(path, "rb") as f:
        head = f.read(128)
    if path.suffix.lower() == ".mat" or head.startswith(b"MATLAB"):
        return _read_mat(path)
    try:
        return json.loads(path.read_text(), object_pairs_hook=lambda pairs: _unique(pairs, path))
    except (ValueError, UnicodeDecodeError) as err:
        raise SceneError(f"{path}: neither JSON (MATLAB's jsonencode) nor a MAT-file ({err})") from None
    except RecursionError:
        raise SceneError(f"{path}: not valid JSON (nested too deeply to read)") from None


def _unique(pairs: list[tuple[str, object]], path: Path) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise SceneError(f"{path}: key '{key}' appears twice in one object; keep one")
        out[key] = value
    return out


def _read_mat(path: Path):
    try:
        import scipy.io
        from scipy.io.matlab import MatReadError
    except ImportError:
        raise SceneError(f"{path}: reading a MAT-file needs scipy: pip install 'flamerecon[matlab]' "
                         "(or write the calibration with MATLAB's jsonencode)") from None
    try:
        data = scipy.io.loadmat(path, simplify_cells=True)
    except NotImplementedError:
        raise SceneError(f"{path}: a MAT-file v7.3 (HDF5), which scipy cannot read; save it with "
                         "save(FILE, VAR, '-v7'), or write it with jsonencode") from None
    except (MatReadError, ValueError, TypeError, OSError) as err:
        raise SceneError(f"{path}: not a MAT-file scipy can read ({' '.join(str(err).split())[:120]})") from None
    variables = {k: v for k, v in data.items() if not k.startswith("__")}
    if not variables:
        raise SceneError(f"{path}: the MAT-file holds no variable")
    return next(iter(variables.values())) if len(variables) == 1 else variables


def _is_camera(value) -> bool:
    return isinstance(value, dict) and any(k in value for k in _INTRINSIC_KEYS)


def _is_stereo(value) -> bool:
    return isinstance(value, dict) and "CameraParameters1" in value and "CameraParameters2" in value


def _items(value) -> list | None:
    """A JSON array or a MAT-file's array of structs as a list, else None."""
    if isinstance(value, list):
        return value
    if isinstance(value, np.ndarray) and value.dtype == object:
        return list(value.reshape(-1))
    return None


def read_matlab_cameras(path: Path) -> tuple[list[MatlabCamera], str]:
    """Every camera of a MATLAB calibration file, in OpenCV's conventions, and what the file
    holds (for the converter's message)."""
    data = read_matlab_file(path)
    if _is_stereo(data):
        return _stereo(data, path), "a stereoParameters (camera 1's frame is the world)"
    if _is_camera(data):
        return [_camera(path.stem, data, path, "")], "one camera"
    listed = _items(data)
    if listed is not None:
        entries = [(f"cam{i + 1}", v, f"[{i}].") for i, v in enumerate(listed)]
        what = "an array of cameras, named cam1, cam2, ..."
    elif isinstance(data, dict):
        entries = [(str(k), v, f"{k}.") for k, v in data.items()]
        what = "a map of cameras"
    else:
        entries, what = [], ""
    if not entries:
        raise SceneError(f"{path}: holds no camera: expected a cameraParameters, a stereoParameters, a map "
                         "from camera name to camera, or an array of cameras")
    for _, value, where in entries:
        if not _is_camera(value):
            kind = "a MATLAB object scipy cannot read (save toStruct(params) instead)" if type(
                value).__name__ == "MatlabOpaque" else "not a camera (no K, IntrinsicMatrix or FocalLength)"
            raise SceneError(f"{path}: {where.rstrip('.')}: {kind}")
    return [_camera(name, value, path, where) for name, value, where in entries], what


def _camera(name: str, entry: dict, path: Path, where: str, posed: bool = True) -> MatlabCamera:
    """A camera's intrinsics and (``posed``) its pose in the rig's world."""
    K, dist, size, intrinsics = _intrinsics(entry, path, where)
    pose = _pose(entry, path, where) if posed else None
    if pose is None and posed:
        raise SceneError(f"{path}: {where}pose: missing; give the camera's pose in the rig's world: "
                         "RotationMatrix and TranslationVector (extrinsics), or Extrinsics (a "
                         "rigidtform3d from estimateExtrinsics)")
    w2c, convention = pose if pose is not None else (np.eye(4), "the world")
    units = entry.get("WorldUnits")
    return MatlabCamera(name, K, dist, w2c, size, intrinsics, convention,
                        units if isinstance(units, str) else None)


def _field(entry: dict, key: str):
    """``entry[key]``, else the same field of its ``Intrinsics`` (a cameraIntrinsics)."""
    if key in entry:
        return entry[key]
    inner = entry.get("Intrinsics")
    return inner.get(key) if isinstance(inner, dict) else None


def _intrinsics(entry: dict, path: Path, where: str):
    """(K OpenCV, dist, (H, W) or None, the convention the intrinsics were written in)."""
    K = matrix = None
    if _field(entry, "K") is not None:
        K = read_matrix(_field(entry, "K"), (3, 3), path, f"{where}K")
        if not _last_row(K) and _last_row(K.T):
            raise SceneError(f"{path}: {where}K: has the layout of pre-R2022b's IntrinsicMatrix (cx, cy in its "
                             "last row); name it IntrinsicMatrix, or give K = IntrinsicMatrix'")
    if _field(entry, "IntrinsicMatrix") is not None:
        matrix = read_matrix(_field(entry, "IntrinsicMatrix"), (3, 3), path, f"{where}IntrinsicMatrix")
        if not _last_row(matrix.T) and _last_row(matrix):
            raise SceneError(f"{path}: {where}IntrinsicMatrix: has the layout of K (cx, cy in its last column); "
                             "name it K, or give IntrinsicMatrix = K'")
    if K is not None and matrix is not None and not _close(K, matrix.T):
        raise SceneError(f"{path}: {where}K: disagrees with IntrinsicMatrix (K must equal IntrinsicMatrix'); "
                         "keep one")
    convention = POST if K is not None else PRE if matrix is not None else "FocalLength/PrincipalPoint"
    K = K if K is not None else matrix.T if matrix is not None else None
    focal, centre = _field(entry, "FocalLength"), _field(entry, "PrincipalPoint")
    if focal is not None or centre is not None:
        f = read_matrix(focal, (2,), path, f"{where}FocalLength")
        c = read_matrix(centre, (2,), path, f"{where}PrincipalPoint")
        skew = float(read_matrix(_field(entry, "Skew") if _field(entry, "Skew") is not None else 0.0, (1,),
                                 path, f"{where}Skew")[0])
        built = np.array([[f[0], skew, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]])
        if K is not None and not _close(K, built):
            raise SceneError(f"{path}: {where}FocalLength/PrincipalPoint: disagree with {convention.split(':')[0]} "
                             f"{'K' if convention == POST else 'IntrinsicMatrix'}; keep one")
        K = built if K is None else K
    if K is None:
        raise SceneError(f"{path}: {where}K: missing (K, IntrinsicMatrix, or FocalLength and PrincipalPoint)")
    if not _last_row(K) or abs(K[1, 0]) > _AGREE:
        raise SceneError(f"{path}: {where}K: not an intrinsics matrix ([fx s cx; 0 fy cy; 0 0 1])")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SceneError(f"{path}: {where}K: focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    K = K.copy()
    K[:2, 2] -= 1.0  # MATLAB's first pixel centre is (1, 1), OpenCV's (0, 0)
    return K, _distortion(entry, path, where), _size(entry, path, where), convention


def _last_row(K: np.ndarray) -> bool:
    return bool(np.allclose(K[2], [0.0, 0.0, 1.0], atol=_AGREE))


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a, b, rtol=_AGREE, atol=_AGREE))


def _distortion(entry: dict, path: Path, where: str) -> list[float]:
    """OpenCV's k1 k2 p1 p2 [k3] from RadialDistortion and TangentialDistortion ([] if none)."""
    radial, tangential = _field(entry, "RadialDistortion"), _field(entry, "TangentialDistortion")
    k = read_array(radial, path, f"{where}RadialDistortion").reshape(-1) if radial is not None else np.zeros(2)
    p = read_array(tangential, path, f"{where}TangentialDistortion").reshape(-1) if tangential is not None \
        else np.zeros(2)
    if k.size not in (2, 3):
        raise SceneError(f"{path}: {where}RadialDistortion: expected [k1 k2] or [k1 k2 k3], got {k.size} values")
    if p.size != 2:
        raise SceneError(f"{path}: {where}TangentialDistortion: expected [p1 p2], got {p.size} values")
    dist = [float(k[0]), float(k[1]), float(p[0]), float(p[1])] + ([float(k[2])] if k.size == 3 else [])
    return dist if any(dist) else []


def _size(entry: dict, path: Path, where: str) -> tuple[int, int] | None:
    value = _field(entry, "ImageSize")
    return None if value is None else read_size(value, path, f"{where}ImageSize", "[rows, cols]")


def _pose(entry: dict, path: Path, where: str) -> tuple[np.ndarray, str] | None:
    """(world->camera OpenCV 4x4, its convention) from the fields a camera may hold, or None.
    A pose given twice (as matrix and rotation vector) must agree."""
    found: list[tuple[str, np.ndarray, str]] = []  # (fields, w2c, convention)
    if isinstance(entry.get("Extrinsics"), dict):
        found.append(("Extrinsics", *_transform(entry["Extrinsics"], path, f"{where}Extrinsics")))
    t = _vector(entry, "TranslationVector", path, where)
    if "RotationMatrix" in entry:
        R = check_rotation(read_matrix(entry["RotationMatrix"], (3, 3), path, f"{where}RotationMatrix"), path,
                           f"{where}RotationMatrix")
        found.append(("RotationMatrix", _w2c(R.T, _needs(t, where, "TranslationVector", path)), PRE))
    if "RotationVector" in entry:
        found.append(("RotationVector", _w2c(_rodrigues(entry["RotationVector"], path, f"{where}RotationVector"),
                                             _needs(t, where, "TranslationVector", path)), "rotation vector"))
    if not found:
        found = _pattern_pose(entry, path, where)
    if not found:
        return None
    first, w2c, convention = found[0]
    for other, again, _ in found[1:]:
        if not _close(w2c, again):
            raise SceneError(f"{path}: {where}{other}: disagrees with {first} ({_angle(w2c, again):.3g} degrees, "
                             f"{np.linalg.norm(w2c[:3, 3] - again[:3, 3]):.3g} world units); keep one")
    return w2c, convention


def _pattern_pose(entry: dict, path: Path, where: str) -> list[tuple[str, np.ndarray, str]]:
    """The pose of a camera calibrated with a single pattern (its pattern extrinsics)."""
    found = []
    if entry.get("PatternExtrinsics") is not None:
        patterns = _items(entry["PatternExtrinsics"])
        patterns = [entry["PatternExtrinsics"]] if patterns is None else patterns
        _one_pattern(len(patterns), path, f"{where}PatternExtrinsics")
        found.append(("PatternExtrinsics", *_transform(patterns[0], path, f"{where}PatternExtrinsics")))
    if "TranslationVectors" in entry:
        t = read_array(entry["TranslationVectors"], path, f"{where}TranslationVectors")
        _one_pattern(1 if t.size == 3 else t.shape[0], path, f"{where}TranslationVectors")
        t = t.reshape(3)
        if "RotationMatrices" in entry:
            R = read_array(entry["RotationMatrices"], path, f"{where}RotationMatrices")
            _one_pattern(1 if R.shape == (3, 3) else R.shape[-1], path, f"{where}RotationMatrices")
            R = check_rotation(R.reshape(3, 3), path, f"{where}RotationMatrices")
            found.append(("RotationMatrices", _w2c(R.T, t), PRE))
        if "RotationVectors" in entry:
            v = read_array(entry["RotationVectors"], path, f"{where}RotationVectors")
            _one_pattern(1 if v.size == 3 else v.shape[0], path, f"{where}RotationVectors")
            found.append(("RotationVectors", _w2c(_rodrigues(v, path, f"{where}RotationVectors"), t),
                          "rotation vector"))
    return found


def _one_pattern(count: int, path: Path, field: str) -> None:
    if count != 1:
        raise SceneError(f"{path}: {field}: holds {count} pattern poses, not the rig's one; give each camera its "
                         "pose in the rig's world: RotationMatrix and TranslationVector (extrinsics), or "
                         "Extrinsics (estimateExtrinsics)")


def _vector(entry: dict, key: str, path: Path, where: str) -> np.ndarray | None:
    return None if key not in entry else read_matrix(entry[key], (3,), path, f"{where}{key}")


def _needs(value, where: str, key: str, path: Path):
    if value is None:
        raise SceneError(f"{path}: {where}{key}: missing (the rotation's translation)")
    return value


def _w2c(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    return w2c


def _rodrigues(value, path: Path, field: str) -> np.ndarray:
    """A MATLAB rotation vector (the same vector in both conventions) as OpenCV's R."""
    return cv2.Rodrigues(read_matrix(value, (3,), path, field))[0]


def _transform(value, path: Path, field: str) -> tuple[np.ndarray, str]:
    """A jsonencoded ``rigidtform3d`` (``R``, ``Translation``, ``A``: premultiply) or legacy
    ``rigid3d`` (``Rotation``, ``Translation``, ``T``: postmultiply) as world->camera."""
    if not isinstance(value, dict):
        raise SceneError(f"{path}: {field}: expected a rigidtform3d (R and Translation, or A)")
    if "Rotation" in value or "T" in value:  # rigid3d, postmultiply: T = [R 0; t 1]
        if "Rotation" in value:
            R = read_matrix(value["Rotation"], (3, 3), path, f"{field}.Rotation").T
            t = read_matrix(value.get("Translation"), (3,), path, f"{field}.Translation")
        else:
            T = read_matrix(value["T"], (4, 4), path, f"{field}.T")
            R, t = T[:3, :3].T, T[3, :3]
        check_rotation(R, path, f"{field}.Rotation")
        return _w2c(R, t), PRE
    A = read_matrix(value["A"], (4, 4), path, f"{field}.A") if "A" in value else None
    if "R" in value:
        R = read_matrix(value["R"], (3, 3), path, f"{field}.R")
        t = read_matrix(value.get("Translation"), (3,), path, f"{field}.Translation")
        if A is not None and not _close(A, _w2c(R, t)):
            raise SceneError(f"{path}: {field}.A: disagrees with R and Translation (A = [R t; 0 0 0 1]); keep one")
    elif A is not None:
        if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0], atol=_AGREE):
            raise SceneError(f"{path}: {field}.A: last row must be [0 0 0 1] (premultiply), got {A[3].tolist()}")
        R, t = A[:3, :3], A[:3, 3]
    else:
        raise SceneError(f"{path}: {field}: expected a rigidtform3d (R and Translation, or A)")
    check_rotation(R, path, f"{field}.R")
    return _w2c(R, t), POST


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def _stereo(data: dict, path: Path) -> list[MatlabCamera]:
    """camera1 at the world's origin, camera2 where the pair's relative pose puts it."""
    first = data["CameraParameters1"]
    second = data["CameraParameters2"]
    for key, value in (("CameraParameters1", first), ("CameraParameters2", second)):
        if not _is_camera(value):
            raise SceneError(f"{path}: {key}: not a camera (no K, IntrinsicMatrix or FocalLength)")
    found = []
    if isinstance(data.get("PoseCamera2"), dict):  # x_cam2 = R x_cam1 + t (world2img's extrinsics)
        found.append(("PoseCamera2", *_transform(data["PoseCamera2"], path, "PoseCamera2")))
    if "RotationOfCamera2" in data:  # x_cam2 = x_cam1 R + t
        R = check_rotation(read_matrix(data["RotationOfCamera2"], (3, 3), path, "RotationOfCamera2"), path,
                           "RotationOfCamera2")
        t = _needs(_vector(data, "TranslationOfCamera2", path, ""), "", "TranslationOfCamera2", path)
        found.append(("RotationOfCamera2", _w2c(R.T, t), PRE))
    if not found:
        raise SceneError(f"{path}: PoseCamera2: missing (or RotationOfCamera2 and TranslationOfCamera2)")
    for other, again, _ in found[1:]:
        if not _close(found[0][1], again):
            raise SceneError(f"{path}: {other}: disagrees with {found[0][0]} "
                             f"({_angle(found[0][1], again):.3g} degrees); keep one")
    one = _camera("camera1", first, path, "CameraParameters1.", posed=False)
    two = _camera("camera2", second, path, "CameraParameters2.", posed=False)
    two.w2c, two.pose_convention = found[0][1], found[0][2]
    return [one, two]
