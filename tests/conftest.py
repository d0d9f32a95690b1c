"""Shared tiny fixtures: a repo path, a small synthetic scene, a box grid and rays through it.

Everything here is small on purpose (grids of 8-24 cells, images of 16-64 px) so that the
whole suite runs in about a minute on two busy CPU cores.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

from flamerecon.grid import VoxelGrid
from flamerecon.projector import Rays

REPO = Path(__file__).resolve().parents[1]


def repo_env() -> dict[str, str]:
    """The environment for a subprocess that imports flamerecon from this checkout: the repo
    put in front of PYTHONPATH (kept, where the packages may come from)."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p))

#: the small synthetic scene the hull and synthetic tests share (keys of scenes/synthetic.py).
SMALL_SCENE = {
    "name": "synthetic", "n_cameras": 6, "width": 64, "height": 48,
    "phantom_resolution": 48, "seed": 0, "frame": 0,
}


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def small_scene():
    """The built-in synthetic flame at 6 cameras x 64x48 px from a 48-cell phantom."""
    from flamerecon.scenes import load_scene

    return load_scene(dict(SMALL_SCENE))


@pytest.fixture
def box_grid() -> VoxelGrid:
    """An asymmetric box (1.0 x 1.5 x 0.75) of 8 x 12 x 6 cubic cells of side 0.125, off
    the origin so that a sign or offset error shows."""
    return VoxelGrid.from_box((-0.3, 0.2, 1.0), (0.7, 1.7, 1.75), (8, 12, 6))


def random_rays(grid: VoxelGrid, n: int, seed: int = 0, radius: float = 3.0) -> Rays:
    """``n`` oblique rays from a sphere of ``radius`` around the box centre towards random
    points inside the box (so most of them cross it)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = grid.lo(), grid.hi()
    center = 0.5 * (lo + hi)
    d = torch.randn(n, 3, generator=g)
    origins = center + radius * torch.nn.functional.normalize(d, dim=-1)
    targets = lo + torch.rand(n, 3, generator=g) * (hi - lo)
    return Rays(origins, torch.nn.functional.normalize(targets - origins, dim=-1))


def ring_of_cameras(n: int, width: int, height: int, target, radius: float = 3.0, focal=None):
    """``n`` look-at cameras on a horizontal ring (world y up) around ``target``."""
    from flamerecon.cameras import intrinsics_matrix, look_at, make_cameras

    target = torch.as_tensor(target, dtype=torch.float32)
    a = torch.arange(n, dtype=torch.float32) * 2 * math.pi / n
    eye = target + torch.stack(
        [radius * torch.sin(a), 0.4 * torch.ones(n), radius * torch.cos(a)], -1
    )
    f = focal if focal is not None else 1.4 * width
    K = intrinsics_matrix(f, f, width / 2, height / 2).expand(n, 3, 3)
    return make_cameras(K, look_at(eye, target.expand(n, 3)), height, width)
