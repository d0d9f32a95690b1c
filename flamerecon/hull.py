"""The visual hull (paper section III-B): voxels that project inside the silhouette in
every training view."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera

from .cameras import project_points
from .grid import VoxelGrid


def carve_counts(grid: VoxelGrid, cams: PinholeCamera, masks: torch.Tensor) -> torch.Tensor:
    """For each camera, the voxels it carves away: (B, nz, ny, nx) bool.

    A camera carves a voxel whose centre projects, in front of it and inside its image,
    onto a pixel outside its silhouette ``masks`` (B, H, W). A voxel the camera does not see
    is kept: that camera cannot refute it.
    """
    device = masks.device
    centers = grid.centers(device).reshape(-1, 3)
    H, W = masks.shape[-2:]
    carved = torch.zeros(cams.batch_size, centers.shape[0], dtype=torch.bool, device=device)
    for s in range(0, centers.shape[0], 1 << 20):
        uv, depth = project_points(cams, centers[s:s + (1 << 20)])
        u, v = torch.floor(uv[..., 0]).long(), torch.floor(uv[..., 1]).long()
        seen = (depth > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        b = torch.arange(cams.batch_size, device=device)[:, None].expand_as(u)
        inside = masks[b, v.clamp(0, H - 1), u.clamp(0, W - 1)]
        carved[:, s:s + (1 << 20)] = seen & ~inside
    return carved.reshape(cams.batch_size, *grid.shape)


def visual_hull(
    grid: VoxelGrid, cams: PinholeCamera, masks: torch.Tensor, margin_voxels: int = 1
) -> torch.Tensor:
    """Candidate region Omega on ``grid``: (nz, ny, nx) bool, grown by ``margin_voxels``
    so that density near the silhouette edge is not carved away."""
    hull = ~carve_counts(grid, cams, masks).any(0)
    if margin_voxels > 0:
        k = 2 * int(margin_voxels) + 1
        hull = F.max_pool3d(hull[None, None].float(), k, stride=1, padding=int(margin_voxels))[0, 0] > 0
    return hull
