"""The cameras of a capture refined once over several of its frames (``calibration.frames``).

The cameras stand still while the flame moves, so their corrections are a property of the
capture, not of a frame: :func:`capture_refinement` fits them to the training views of the
frames listed (:func:`flamerecon.fit.refine_cameras.refine` with one density per frame) and keeps
the result in the disk cache (:mod:`flamerecon.scenes.cache`), so every frame of a sequence
reuses one fit. The entry is named by the frames' training images, the calibration, the
training views, the options and the code that fits them: any change fits again.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import asdict

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon import solvers
from flamerecon.fit import build, debias, refine_cameras
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.refine_cameras import CalibrationFrame, Refinement, refine
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import projector
from flamerecon.scenes import Scene, load_frame
from flamerecon.scenes.cache import cached, digest

#: history keys of a refinement round, in the order the cache stores them
ROUND_KEYS = ("rms_before", "rms_after", "iterations", "rays")


def capture_refinement(scene: Scene, train: list[int], grid: VoxelGrid, options: ReconstructionOptions,
                       device: torch.device, frame_of: Callable[[Scene], CalibrationFrame]) -> Refinement:
    """The training cameras ``train`` of ``scene`` refined over the frames
    ``options.calibration.frames`` of its capture (each loaded as :func:`load_frame` does and
    turned into a :class:`CalibrationFrame` by ``frame_of``), from the cache when it holds
    them. ``initial_volume`` is None: no frame of the fit need be the one reconstructed."""
    frames = [load_frame(scene, t) for t in options.calibration.frames]  # refuses a scene without config
    images = {f"frame{t}": f.images[train] for t, f in zip(options.calibration.frames, frames)}
    key = {
        "capture": {k: v for k, v in scene.meta["config"].items() if k != "frame"},
        "views": [scene.views[v] for v in train],
        "images": digest(images),
        "cameras": digest({"K": scene.cameras.intrinsics, "E": scene.cameras.extrinsics}),
        "options": {k: v for k, v in asdict(options).items() if k not in ("holdout", "threads", "init")},
        "device": torch.device(device).type,
        "step": float(options.projector.step),
    }

    def compute() -> dict[str, torch.Tensor]:
        found = refine(cameras_to(scene.cameras, device), train, [frame_of(f) for f in frames], grid,
                       options.calibration, float(options.projector.step))
        history = torch.tensor([[float(r[k]) for k in ROUND_KEYS] for r in found.history], dtype=torch.float64)
        return {"intrinsics": found.cameras.intrinsics.cpu(), "extrinsics": found.cameras.extrinsics.cpu(),
                "corrections": found.corrections.cpu(), "history": history.reshape(-1, len(ROUND_KEYS))}

    tensors = cached("calibration", key, compute,
                     [refine_cameras, projector, build, debias, *solver_modules()])
    cameras = PinholeCamera(tensors["intrinsics"], tensors["extrinsics"], scene.cameras.height.clone(),
                            scene.cameras.width.clone())
    history = [{k: (int(v) if k in ("iterations", "rays") else float(v)) for k, v in zip(ROUND_KEYS, row.tolist())}
               for row in tensors["history"]]
    return Refinement(cameras, tensors["corrections"], None, history)


def solver_modules() -> list:
    """The modules of :mod:`flamerecon.solvers` (their code shapes every density solve)."""
    return [importlib.import_module(f"{solvers.__name__}.{m.name}") for m in pkgutil.iter_modules(solvers.__path__)]
