"""A frame's velocity on disk: ``velocity.npz`` beside its ``density.npz`` in the frame's run
folder, and as VTK vector fields.

``velocity.npz`` holds ``velocity`` float32 (3, nz, ny, nx), components (x, y, z) in world
units per second (metres per second for ScalarFlow), at the same cell centres as the density
(``bbox_min``, ``bbox_max``: the density file's box); ``frame`` (the frame it starts from; it
carries that frame onto ``frame + 1``), ``frame_rate`` (frames per second) and ``record`` (JSON:
how the fit went, :meth:`flamerecon.dynamics.flow.PairFlow.record`, and the options). A velocity in
cells per frame is ``velocity / (cell size * frame_rate)``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from flamerecon.errors import FlameReconError
from flamerecon.outputs.atomic import save_npz_atomic
from flamerecon.outputs.export import voxel_size

VELOCITY_FILE = "velocity.npz"
_FIELDS = ("velocity", "bbox_min", "bbox_max", "frame", "frame_rate", "record")


class VelocityFileError(FlameReconError, ValueError):
    """A velocity file that is missing a field or holds one of the wrong shape or type."""


class Velocity(NamedTuple):
    """What ``velocity.npz`` holds."""

    velocity: np.ndarray  # float32 (3, nz, ny, nx), world units per second
    bbox_min: np.ndarray  # (3,) world xyz
    bbox_max: np.ndarray
    frame: int
    frame_rate: float
    record: dict

    def cells_per_frame(self) -> np.ndarray:
        """The velocity (3, nz, ny, nx) in cells per frame."""
        size = voxel_size(self.bbox_min, self.bbox_max, self.velocity.shape)
        return self.velocity / (size.reshape(3, 1, 1, 1) * self.frame_rate)


def _check(where: str, velocity: np.ndarray, bbox_min: np.ndarray, bbox_max: np.ndarray) -> None:
    """Refuse a velocity that is not float (3, nz, ny, nx) and finite, or a box that is not
    two ordered, finite world points, naming ``where`` and the field."""
    if velocity.ndim != 4 or velocity.shape[0] != 3 or min(velocity.shape) < 1:
        raise VelocityFileError(f"{where}: field 'velocity' must have shape (3, nz, ny, nx), got {velocity.shape}")
    if not np.issubdtype(velocity.dtype, np.floating) or not np.isfinite(velocity).all():
        raise VelocityFileError(f"{where}: field 'velocity' must be finite floating point, got "
                                f"{velocity.dtype}{' holding NaN or Inf' if velocity.dtype.kind == 'f' else ''}")
    for name, box in (("bbox_min", bbox_min), ("bbox_max", bbox_max)):
        if box.shape != (3,) or not np.issubdtype(box.dtype, np.number) or not np.isfinite(box).all():
            raise VelocityFileError(f"{where}: field '{name}' must be 3 finite numbers (world xyz), got {box!r}")
    if np.any(bbox_max <= bbox_min):
        raise VelocityFileError(f"{where}: 'bbox_max' {bbox_max} must exceed 'bbox_min' {bbox_min}")


def velocity_path(run_dir_or_file: str | os.PathLike) -> Path:
    """``velocity.npz`` of a run folder, or the file itself."""
    path = Path(run_dir_or_file)
    return path / VELOCITY_FILE if path.is_dir() else path


def save_velocity(path: str | os.PathLike, velocity, bbox_min, bbox_max, frame: int, frame_rate: float,
                  record: dict) -> Path:
    """Write ``velocity.npz`` (module doc) atomically; ``velocity`` (3, nz, ny, nx) in world units
    per second."""
    vel = np.asarray(velocity, dtype=np.float32)
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(-1) for b in (bbox_min, bbox_max))
    _check(str(path), vel, lo, hi)
    return save_npz_atomic(Path(path), velocity=vel, bbox_min=lo, bbox_max=hi, frame=np.int64(frame),
                           frame_rate=np.float64(frame_rate), record=np.array(json.dumps(record)))


def load_velocity(path: str | os.PathLike) -> Velocity:
    """Read and check ``velocity.npz`` (or the one of a run folder). FileNotFoundError when it is
    missing, :class:`VelocityFileError` naming the file and the field for anything else."""
    path = velocity_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no velocity file (scripts/flow.py writes {VELOCITY_FILE} into a "
                                "sequence's run folders)")
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as err:  # numpy raises several types for a damaged or foreign file
        raise VelocityFileError(f"{path}: not a readable .npz archive ({err})") from err
    with archive:
        missing = [name for name in _FIELDS if name not in archive.files]
        if missing:
            raise VelocityFileError(f"{path}: missing field '{missing[0]}' (has {sorted(archive.files)})")
        try:
            got = {name: archive[name] for name in _FIELDS}
        except ValueError as err:
            raise VelocityFileError(f"{path}: a field cannot be read ({err})") from err
    vel = got["velocity"]
    _check(str(path), vel, got["bbox_min"], got["bbox_max"])
    try:
        record = json.loads(str(got["record"]))
        frame, rate = int(got["frame"]), float(got["frame_rate"])
    except (TypeError, ValueError) as err:
        raise VelocityFileError(f"{path}: field 'record', 'frame' or 'frame_rate' cannot be read ({err})") from err
    if not rate > 0:
        raise VelocityFileError(f"{path}: field 'frame_rate' must be > 0, got {rate}")
    return Velocity(vel.astype(np.float32, copy=False), got["bbox_min"].astype(np.float64),
                    got["bbox_max"].astype(np.float64), frame, rate, record)
