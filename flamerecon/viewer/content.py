"""What the viewer shows, free of any server: the frames of a reconstruction (one for a run, one
per frame for a multirun or an assembled sequence), each its density, grid, scene (cameras and
captured images) and held-out scores, loaded when first asked for."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flamerecon.errors import RunFolderError
from flamerecon.fit.reconstruct import Reconstruction
from flamerecon.geometry.axes import up_vector
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.outputs.export import DENSITY_FILE
from flamerecon.outputs.sequence import SweepError, find_frame_runs
from flamerecon.run.folder import CONFIG_FILE, Run, load_run
from flamerecon.scenes import Scene

#: the scores shown per held-out camera, with their labels
SCORE_KEYS = (("psnr", "PSNR dB"), ("psnr_black", "black dB"), ("ssim", "SSIM"), ("detail", "detail"))


@dataclass
class ViewFrame:
    """One frame as the viewer shows it."""

    label: str  # "frame 59" or the run folder's name
    density: torch.Tensor  # (C, nz, ny, nx) emission density, world units
    grid: VoxelGrid
    scene: Scene  # cameras (OpenCV world->camera) and captured images (B, C, H, W) in [0, 1]
    train: list[int]
    holdout: list[int]
    scores: dict  # held-out view name -> {psnr, psnr_black, ssim, detail, ...}
    train_psnr: float | None  # mean over the training views

    @property
    def up(self) -> np.ndarray:
        """The scene's up axis (``scene.up``) as a unit world vector (3,)."""
        return np.asarray(up_vector(self.scene.up))


def frame_of_run(run: Run | Reconstruction, label: str) -> ViewFrame:
    """A loaded run folder or a Reconstruction as a frame; its held-out scores from its
    metrics.json, or computed (a Reconstruction, or a run without metrics.json)."""
    if isinstance(run, Reconstruction):
        metrics, train, holdout = run.score(), run.setup.train, run.setup.holdout
    else:
        metrics = run.metrics if run.metrics.get("heldout") else run.score()
        train, holdout = run.train, run.holdout
    train_scores = [v.get("psnr") for v in metrics.get("train", {}).values() if v.get("psnr") is not None]
    return ViewFrame(label, run.density.detach(), run.grid, run.scene, list(train), list(holdout),
                     dict(metrics.get("heldout", {})), float(np.mean(train_scores)) if train_scores else None)


class Frames:
    """The frames of what ``flamerecon view`` was given, in time order, each loaded on first use
    (a sequence's scenes read their captures) and kept. ``labels``: one per frame."""

    def __init__(self, labels: list[str], load: Callable[[int], ViewFrame]) -> None:
        self.labels = labels
        self._load = load
        self._cache: dict[int, ViewFrame] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, index: int) -> ViewFrame:
        with self._lock:
            if index not in self._cache:
                self._cache[index] = self._load(index)
            return self._cache[index]


def frames_of(source: Reconstruction | Run | str | os.PathLike, device: str = "auto") -> Frames:
    """The frames of a Reconstruction, a loaded Run, a run folder, or a folder of runs (a Hydra
    multirun of frames, assembled by ``scripts/assemble.py`` or not): one frame each, in frame
    order. A folder that is neither is a :class:`~flamerecon.errors.RunFolderError` naming it."""
    if isinstance(source, (Reconstruction, Run)):
        label = f"frame {source.scene.meta.get('config', {}).get('frame', 0)}"
        return Frames([label], lambda _: frame_of_run(source, label))
    folder = Path(source)
    if not folder.is_dir():
        raise RunFolderError(f"{folder}: no such folder; give a run folder (outputs/DATE/TIME) or a "
                             "multirun folder (multirun/DATE/TIME)")
    if (folder / DENSITY_FILE).is_file():
        return Frames([folder.name], lambda _: frame_of_run(load_run(folder, device), folder.name))
    try:
        runs = find_frame_runs(folder, skip_incomplete=True)
    except SweepError as err:
        raise RunFolderError(f"{folder}: neither a run folder ({DENSITY_FILE}, {CONFIG_FILE}) nor a "
                             f"multirun of them ({err})") from None
    labels = [f"frame {r.frame}" for r in runs]
    return Frames(labels, lambda i: frame_of_run(load_run(runs[i].run_dir, device), labels[i]))
