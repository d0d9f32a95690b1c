"""Rays, cameras and hulls for the projector and operator tests."""

from __future__ import annotations

import math

import torch

from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import Rays


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
    from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras

    target = torch.as_tensor(target, dtype=torch.float32)
    a = torch.arange(n, dtype=torch.float32) * 2 * math.pi / n
    eye = target + torch.stack(
        [radius * torch.sin(a), 0.4 * torch.ones(n), radius * torch.cos(a)], -1
    )
    f = focal if focal is not None else 1.4 * width
    K = intrinsics_matrix(f, f, width / 2, height / 2).expand(n, 3, 3)
    return make_cameras(K, look_at(eye, target.expand(n, 3)), height, width)


def random_hull(grid: VoxelGrid, fraction: float = 0.4, seed: int = 0) -> torch.Tensor:
    """A random subset of flat voxel indices, sorted (M,)."""
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(grid.num_voxels, generator=g) < fraction).nonzero().squeeze(1)
