"""The Python API's own pieces: scenes by name, rendering and scoring in one call each. The
rest of the API (options, build, fit, reconstruct, load_run) is re-exported from
:mod:`flamerecon` where it lives."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.scenes import Scene
from flamerecon.scenes import load_scene as load_scene_node


def load_scene(scene: str | Mapping, **options) -> Scene:
    """A scene by loader name (``"synthetic"``, ``"scalarflow"``, ``"opencv"``, ``"nerf"``,
    ``"pinf"``) or by its options mapping (``{"name": ..., ...}`` as ``conf/scene/*.yaml``
    has them), with ``options`` on top, e.g. ``load_scene("synthetic", width=64, height=48)``."""
    node = {"name": scene} if isinstance(scene, str) else dict(scene)
    return load_scene_node({**node, **options})


def render(volume: torch.Tensor, grid: VoxelGrid, cameras, step: float = 0.5) -> torch.Tensor:
    """Emission-only renders of a density (C, nz, ny, nx) on ``grid`` through kornia
    ``cameras`` (B of them, one size): (B, C, H, W) line integrals, ``step`` in voxels."""
    return render_image(volume, grid, cameras_to(cameras, volume.device), step)


def score(result) -> dict:
    """The metrics of a :class:`~flamerecon.fit.reconstruct.Reconstruction` or a loaded
    :class:`~flamerecon.run.folder.Run`: held-out and training PSNR / SSIM (with the all-black
    floor), inside the silhouettes, and volume errors when the scene has a truth."""
    return result.score()
