"""The cameras of a capture refined once over several of its frames (``calibration.frames``),
kept as a cameras.json file.

The cameras stand still while the flame moves, so their corrections are a property of the
capture, not of a frame: :func:`capture_refinement` fits them to the training views of the
frames listed (:func:`flamerecon.fit.refine_cameras.refine` with one density per frame) and
writes them once (:mod:`flamerecon.outputs.cameras_file`) to
``<calibration.folder>/<capture>/cameras-<key>.json``; every later run, script and API call with
the same key reads that file instead of fitting. The default folder is ``calibration/`` in the
cache folder (:func:`flamerecon.scenes.cache.cache_home`): per user and writable, where a data
folder is often read-only or shared, and never in the checkout; unlike a cache entry nothing
evicts it. The key hashes what determines the cameras: the frames' training images, the
capture's calibration, the training views, the grid of the fit, the options of the fit and of
its density solves, the device type and the code that fits them; any change fits again, into
a file of its own.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon import solvers
from flamerecon.errors import ConfigError
from flamerecon.evaluate import pose_spread
from flamerecon.fit import build, debias, pose_uncertainty, refine_cameras, weight_selection
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.pose_uncertainty import PoseOffset, capture_offsets, spread
from flamerecon.fit.refine_cameras import CalibrationFrame, found_nothing, refine, with_cameras
from flamerecon.geometry.cameras import camera_subset, cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import projector
from flamerecon.outputs import cameras_file
from flamerecon.outputs.atomic import make_folder, write_json_atomic
from flamerecon.outputs.cameras_file import camera_records, cameras_from_records, read_camera_file
from flamerecon.scenes import Scene, load_frame
from flamerecon.scenes.cache import cache_home, digest, entry_key

log = logging.getLogger(__name__)

#: options that do not change the cameras fitted: views held out (the training views are keyed),
#: warm start, threads, the device (its type is keyed), the run's grid (the fit's is keyed), the
#: resolution ladder (the fit runs on one rung's images, which are keyed) and the confidence
#: computed after the solve
UNKEYED = ("holdout", "init", "threads", "device", "grid", "ladder", "uncertainty")


@dataclass
class CaptureCalibration:
    """The training cameras of a capture: ``cameras`` (B: every camera of the scene, the
    held-out ones the scene's own), the fit's rounds (``history``, as
    :class:`~flamerecon.fit.refine_cameras.Refinement` has them) and ``source``: ``fitted``
    (now, and written to ``file``) or ``read`` (from ``file``)."""

    cameras: PinholeCamera
    history: list[dict]
    source: str
    file: Path | None
    selection: dict | None = None  # select.auto's record of the capture's weights (chosen on the frames)
    offsets: dict[str, PoseOffset] | None = None  # each camera's pose offset (fit/pose_uncertainty.py), by name


def capture_refinement(scene: Scene, train: list[int], grid: VoxelGrid, options: ReconstructionOptions,
                       device: torch.device, frame_of: Callable[[Scene, dict | None], CalibrationFrame],
                       choose: Callable[[PinholeCamera, list[Scene], str], dict | None] | None = None
                       ) -> CaptureCalibration:
    """The training cameras ``train`` of ``scene`` refined over the frames
    ``options.calibration.frames`` of its capture (each loaded as :func:`load_frame` does and
    turned into a :class:`CalibrationFrame` by ``frame_of(frame, weights)``), read from the
    capture's calibration file when it exists, else fitted and written there. The cameras' pose
    offsets are measured with them where ``calibration.offsets`` or the confidence asks for them
    (:func:`kept_offsets` adds them to a file kept without).
    ``choose(cameras, frames, which)``: the selection record of the capture's solver weights,
    chosen on those frames (None: none), first with the capture's own cameras (the weights of
    the fit's densities), then, where the fit corrected the cameras, again with the fitted ones;
    kept in the file for every later frame. A fit that found nothing to correct
    (:func:`~flamerecon.fit.refine_cameras.found_nothing`) keeps the first choice: the cameras
    it was made with stand."""
    frames = [load_frame(scene, t) for t in options.calibration.frames]  # refuses a scene without config
    images = {f"frame{t}": f.images[train] for t, f in zip(options.calibration.frames, frames)}
    others = [v for v in range(scene.num_views) if v not in train]  # their images measure their pose offsets
    images.update({f"frame{t}-others": f.images[others] for t, f in zip(options.calibration.frames, frames)})
    key = entry_key("calibration", calibration_key(scene, train, grid, options, device, images),
                    [*fitting_code(), sys.modules[frame_of.__module__]])
    folder = Path(options.calibration.folder) if options.calibration.folder else cache_home() / "calibration"
    path = folder / capture_name(scene) / f"cameras-{key[:16]}.json"
    wanted = options.calibration.offsets or options.uncertainty.enabled  # the pose offsets, where used
    stored = read_calibration(path, key)
    if stored is not None:
        cameras = file_cameras(path, scene, train)
        offsets = file_offsets(path, scene.views)
        if wanted and not offsets:  # a calibration kept without them: measured now, once, into its file
            weights = (stored.get("selection") or {}).get("chosen")
            offsets = kept_offsets(path, scene, [frame_of(f, weights) for f in frames], cameras, train, grid, options)
        return CaptureCalibration(cameras, list(stored["history"]), "read", path, stored.get("selection"), offsets)
    first = None if choose is None else choose(scene.cameras, frames, "the capture's own")
    fitting = [frame_of(f, None if first is None else first["chosen"]) for f in frames]
    found = refine(cameras_to(scene.cameras, device), train, fitting, grid, options.calibration,
                   float(options.projector.step))
    selection = first if first is None or found_nothing(found.history) else choose(found.cameras, frames,
                                                                                    "the fitted")
    records = camera_records(scene.views, cameras_to(found.cameras, "cpu"), train, calibrated=scene.cameras)
    if wanted:  # on densities solved with the weights kept in the file, as a later run measures them
        measuring = fitting if selection is first else [frame_of(f, selection["chosen"]) for f in frames]
        add_pose_records(records, scene, cameras_to(found.cameras, "cpu"),
                         capture_offsets(measuring, found.cameras, train, grid, options.calibration,
                                         float(options.projector.step), options.calibration.frames), grid)
    record = {"key": key, "frames": list(options.calibration.frames), "refine": options.calibration.refine,
              "history": found.history, "selection": selection}
    try:
        make_folder(path.parent)
        write_json_atomic(path, {"cameras": records, "calibration": record})
    except OSError as err:
        log.warning("could not write the capture's calibration %s (%s): the next run fits it again; set "
                    "calibration.folder to a writable folder", path, err)
    cameras = cameras_from_records(records, scene.views, scene.cameras.height, scene.cameras.width)
    return CaptureCalibration(with_cameras(scene.cameras, train, camera_subset(cameras, train)), found.history,
                              "fitted", path, selection, file_offsets(path, scene.views, records))


def kept_offsets(path: Path, scene: Scene, fitting: list[CalibrationFrame], cameras: PinholeCamera, train: list[int],
                 grid: VoxelGrid, options: ReconstructionOptions) -> dict[str, PoseOffset] | None:
    """The pose offsets of every camera of ``scene`` measured on the calibration frames
    ``fitting`` with the cameras (B) the calibration file ``path`` holds, written into that file
    (its cameras and key unchanged); returned by name."""
    data = read_camera_file(path)
    offsets = capture_offsets(fitting, cameras, train, grid, options.calibration, float(options.projector.step),
                              options.calibration.frames)
    add_pose_records(data["cameras"], scene, cameras_to(cameras, "cpu"), offsets, grid)
    try:
        write_json_atomic(path, data)
    except OSError as err:
        log.warning("could not add the cameras' pose offsets to %s (%s): the next run that needs them measures "
                    "them again", path, err)
    return file_offsets(path, scene.views, data["cameras"])


def calibration_key(scene: Scene, train: list[int], grid: VoxelGrid, options: ReconstructionOptions,
                    device: torch.device, images: dict[str, torch.Tensor]) -> dict:
    """What the cameras fitted by :func:`capture_refinement` depend on, JSON-able."""
    fit_options = {k: v for k, v in options.as_dict().items() if k not in UNKEYED}
    fit_options["calibration"] = {k: v for k, v in fit_options["calibration"].items()
                                 if k not in ("folder", "file", "resolution", "score_before", "offsets")}  # the grid
    # is keyed; the pose offsets are added to the file where a run needs them
    fit_options["projector"] = {k: v for k, v in fit_options["projector"].items() if k != "reuse"}  # same operator
    return {
        "views": [scene.views[v] for v in train],
        "images": digest(images),
        "cameras": digest({"K": scene.cameras.intrinsics, "E": scene.cameras.extrinsics}),
        "grid": {"lo": list(grid.bbox_min), "hi": list(grid.bbox_max), "resolution": list(grid.resolution)},
        "options": fit_options,
        "device": torch.device(device).type,
    }


def read_calibration(path: Path, key: str) -> dict | None:
    """The ``calibration`` record (the fit's ``history``, the capture's weight ``selection``) of the
    calibration file ``path`` when it holds the calibration ``key``; None when there is none
    (or it is unreadable or another's: it is fitted again)."""
    if not path.is_file():
        return None
    try:
        data = read_camera_file(path)
        if data["calibration"]["key"] == key:
            return {"history": list(data["calibration"]["history"]), "selection": data["calibration"].get("selection")}
    except (ConfigError, KeyError, TypeError) as err:
        log.warning("%s is not a calibration file (%s); fitting the cameras again", path, err)
        return None
    log.warning("%s holds another calibration (its key differs); fitting the cameras again", path)
    return None


def file_cameras(path: str | Path, scene: Scene, views: list[int]) -> PinholeCamera:
    """The cameras of ``scene`` with those of ``views`` (the training ones; every one for a rig)
    read from the cameras.json ``path`` (by name; ``calibration.file``) and the others its own."""
    records = read_camera_file(path)["cameras"]
    read = cameras_from_records(records, scene.views, scene.cameras.height, scene.cameras.width,
                                f"calibration.file: {path}")
    return with_cameras(scene.cameras, views, camera_subset(read, views))


def add_pose_records(records: list[dict], scene: Scene, cameras: PinholeCamera, offsets: dict[int, PoseOffset],
                     grid: VoxelGrid) -> None:
    """Each camera's pose uncertainty into its cameras.json record: ``pose_offset`` (the
    :class:`~flamerecon.fit.pose_uncertainty.PoseOffset`), ``pose_sigma_deg``,
    ``pose_sigma_box_px``, ``pose_share`` and ``pose_source``
    (:meth:`~flamerecon.evaluate.pose_spread.PoseSpread.records`)."""
    named = {scene.views[v]: found for v, found in offsets.items()}
    fitted = {r["name"] for r in records if r["split"] == "train"}
    summary = spread(cameras, list(scene.views), named, grid, fitted).records()
    for record in records:
        if record["name"] in named:
            record.update(pose_offset=named[record["name"]].record(), **summary[record["name"]])


def file_offsets(path: str | Path, views: list[str], records: list[dict] | None = None) -> dict[str, PoseOffset] | None:
    """The pose offsets of the cameras ``views`` that the cameras.json ``path`` (or its
    ``records``, already read) holds, by name; None when it holds none (a file written before
    pose offsets were measured, or a run's)."""
    records = read_camera_file(path)["cameras"] if records is None else records
    found = {r["name"]: PoseOffset.from_record(r["pose_offset"]) for r in records
             if isinstance(r, dict) and r.get("name") in views and isinstance(r.get("pose_offset"), dict)}
    return found or None


def capture_name(scene: Scene) -> str:
    """The folder name of a capture's calibration files: the loader's name and the data
    folder's (``scalarflow-scalarflow_real``), letters, digits, ``-``, ``_``, ``.`` only."""
    root = (scene.meta.get("config") or {}).get("root")
    name = f"{scene.name}-{Path(str(root)).name}" if root else scene.name
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


def fitting_code() -> list:
    """The modules whose code shapes the cameras fitted: the fit, the renderer, the density
    solves (set-up, weights, debiasing, every solver), the cameras' pose offsets and the cameras file."""
    found = [importlib.import_module(f"{solvers.__name__}.{m.name}") for m in pkgutil.iter_modules(solvers.__path__)]
    return [refine_cameras, pose_uncertainty, pose_spread, projector, build, debias, weight_selection, cameras_file, *found]
