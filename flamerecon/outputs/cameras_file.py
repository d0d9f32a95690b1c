"""``cameras.json``: the cameras of a scene by name, as every run writes them and as a capture's
refined calibration is kept (:mod:`flamerecon.fit.capture_calibration`).

``{"cameras": [{"name", "K" (3, 3) pixels, "world_to_camera" (4, 4) OpenCV, "width", "height",
"split": "train" | "holdout", "gain", "offset", and after a refinement "K_calibrated",
"world_to_camera_calibrated": the capture's own; in a capture's calibration file also each
camera's pose uncertainty, measured with the fit (:mod:`flamerecon.fit.pose_uncertainty`):
"pose_sigma_deg" (one sigma, degrees), "pose_sigma_box_px" (the box's corners' shift in its
image, pixels), "pose_share", "pose_source" and "pose_offset" (the offset and its figures)},
...], ...}``; other top-level keys (a capture calibration's ``"calibration"`` record) are kept
for the reader. Values are written
from float32 tensors as exact decimals, so a file read back gives the very same cameras.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.errors import ConfigError
from flamerecon.geometry.cameras import K_of, make_cameras
from flamerecon.plain import json_value


def camera_records(names: Sequence[str], cameras: PinholeCamera, train: Sequence[int],
                   photometry: Mapping[str, tuple[float, float]] | None = None,
                   calibrated: PinholeCamera | None = None) -> list[dict]:
    """One record per camera of ``cameras`` (B, named ``names``): K, world_to_camera, size, its
    role (``train`` when its index is in ``train``), ``gain`` / ``offset`` (image = gain *
    integral + offset; from ``photometry``, else 1 and 0) and, with ``calibrated`` (the capture's
    own cameras before a refinement), ``K_calibrated`` and ``world_to_camera_calibrated``."""
    K, E = K_of(cameras).cpu(), cameras.extrinsics.cpu()
    photometry = photometry or {}
    records = []
    for i, name in enumerate(names):
        gain, offset = photometry.get(name, (1.0, 0.0))
        record = {"name": name, "K": K[i].tolist(), "world_to_camera": E[i].tolist(),
                  "width": int(cameras.width[i]), "height": int(cameras.height[i]),
                  "split": "train" if i in train else "holdout", "gain": gain, "offset": offset}
        if calibrated is not None:
            record["K_calibrated"] = K_of(calibrated)[i].cpu().tolist()
            record["world_to_camera_calibrated"] = calibrated.extrinsics[i].cpu().tolist()
        records.append(record)
    return records


def read_camera_file(path: str | Path, field: str = "calibration.file") -> dict:
    """The JSON object of the cameras file ``path``; a :class:`~flamerecon.errors.ConfigError`
    naming ``field`` and the file when it is missing or not a cameras.json."""
    path = Path(path)
    try:
        data = json_value(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{field}: {path} does not exist; give a cameras.json (a run's, or a "
                          "capture's calibration file)") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"{field}: {path} is not a readable JSON file ({err}); give a cameras.json") from None
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), list):
        raise ConfigError(f"{field}: {path} has no \"cameras\" list; give a cameras.json")
    return data


def cameras_from_records(records: list, names: Sequence[str], height: torch.Tensor, width: torch.Tensor,
                         where: str = "cameras.json") -> PinholeCamera:
    """The cameras ``names`` (in that order) of cameras.json ``records``, with image sizes
    ``height`` / ``width`` (B,); a :class:`~flamerecon.errors.ConfigError` naming ``where`` when
    a camera is missing, malformed or recorded at another image size."""
    by_name = {r.get("name"): r for r in records if isinstance(r, dict)}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise ConfigError(f"{where}: no camera named {missing} (it has {sorted(map(str, by_name))}); "
                          "give the cameras file of this capture")
    try:
        K = torch.tensor([by_name[n]["K"] for n in names], dtype=torch.float32)
        E = torch.tensor([by_name[n]["world_to_camera"] for n in names], dtype=torch.float32)
        sizes = [(int(by_name[n]["height"]), int(by_name[n]["width"])) for n in names]
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"{where}: a camera lacks K (3x3), world_to_camera (4x4), width or height ({err})") from None
    if K.shape[1:] != (3, 3) or E.shape[1:] != (4, 4) or not (K.isfinite().all() and E.isfinite().all()):
        raise ConfigError(f"{where}: K must be 3x3 and world_to_camera 4x4, finite; got {tuple(K.shape[1:])} "
                          f"and {tuple(E.shape[1:])}")
    wanted = [(int(h), int(w)) for h, w in zip(height.tolist(), width.tolist())]
    if sizes != wanted:
        raise ConfigError(f"{where}: its cameras are {sizes} pixels (height, width), the scene's {wanted}; "
                          "give a file made at this scene's resolution (scene.downscale)")
    return make_cameras(K, E, height, width)
