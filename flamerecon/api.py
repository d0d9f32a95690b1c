"""The Python API's own pieces: presets and scenes by name as the command line has them,
rendering, scoring and exporting in one call each. The rest of the API (options, build, fit,
reconstruct, load_run, cameras) is re-exported from :mod:`flamerecon` where it lives."""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from flamerecon.fit.options import ReconstructionOptions
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.outputs.export import Density, export_density, load_density
from flamerecon.outputs.mesh import DEFAULT_ISO
from flamerecon.resources import config_dir
from flamerecon.scenes import Scene
from flamerecon.scenes import load_scene as load_scene_node


def preset(scene: str = "synthetic", *overrides: str) -> ReconstructionOptions:
    """The options ``python train.py scene=<scene> <overrides...>`` reconstructs with, composed
    from the same ``conf/`` files by Hydra: ``preset("scalarflow")``, ``preset("synthetic",
    "solver=fista", "grid.resolution=48")``. Scenes: ``conf/scene/*.yaml``."""
    from flamerecon.run.preset import preset as composed

    return composed(scene, *overrides)


def load_scene(scene: str | Mapping = "synthetic", **options) -> Scene:
    """A scene as the command line loads it: by preset name (``"synthetic"``, ``"scalarflow"``:
    the ``scene:`` node of ``conf/scene/<name>.yaml``, e.g. ScalarFlow frame 59 at 1/4
    resolution from ``$FLAMERECON_DATA`` or ``../shared/data/scalarflow_real``), by loader name
    (``"pinf"``), or by its options mapping (``{"name": ..., ...}``); ``options`` on top, e.g.
    ``load_scene("scalarflow", frame=25)`` or ``load_scene("opencv", root="capture/")``."""
    node = {"name": scene} if isinstance(scene, str) else dict(scene)
    if isinstance(scene, str) and (config_dir() / "scene" / f"{scene}.yaml").is_file():
        from flamerecon.run.preset import scene_preset  # Hydra composes it, as for the command line

        node = scene_preset(scene)
    return load_scene_node({**node, **options})


def render(volume: torch.Tensor, grid: VoxelGrid, cameras, step: float = 0.5) -> torch.Tensor:
    """Emission-only renders of a density (C, nz, ny, nx) on ``grid`` through kornia
    ``cameras`` (B of them, one size; :func:`flamerecon.look_at_camera`,
    :func:`flamerecon.orbit_cameras` or a scene's): (B, C, H, W) line integrals, ``step`` in
    voxels."""
    return render_image(volume, grid, cameras_to(cameras, volume.device), step)


def score(result) -> dict:
    """The metrics of a :class:`~flamerecon.fit.reconstruct.Reconstruction` or a loaded
    :class:`~flamerecon.run.folder.Run`: held-out and training PSNR / SSIM (with the all-black
    floor), inside the silhouettes, and volume errors when the scene has a truth."""
    return result.score()


def export(result, stem: str | os.PathLike, formats: Iterable[str] | str = ("vti",),
           iso: float = DEFAULT_ISO) -> list[Path]:
    """Write the density of ``result`` (a Reconstruction, a loaded Run, or a run folder or
    density.npz) for other tools as ``<stem>.<format>``: ``vti`` (ParaView), ``nrrd``, ``raw``
    (+ ``.raw.json``), the iso-surface mesh at ``iso`` times the peak density as ``ply`` and
    ``obj`` (Blender, ParaView; ``mesh``: both), ``all``; returns the files written."""
    if isinstance(result, (str, os.PathLike)):
        volume = load_density(result)
    else:
        views = getattr(result, "train", None) or result.setup.train
        grid = result.grid
        volume = Density(result.density.detach().cpu().numpy().astype(np.float32), np.array(grid.bbox_min),
                         np.array(grid.bbox_max), [result.scene.views[v] for v in views])
    Path(stem).parent.mkdir(parents=True, exist_ok=True)
    return export_density(volume, stem, formats, iso)
