"""The visual hull (paper section III-B): voxels that project inside the silhouette in
every training view."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera

from flamerecon.geometry.cameras import project_points
from flamerecon.geometry.grid import VoxelGrid


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


def hull_footprint(grid: VoxelGrid, cams: PinholeCamera, hull: torch.Tensor) -> torch.Tensor:
    """Pixels whose ray can meet the trilinear support of the hull: (B, H, W) bool.

    The interpolant of values on the hull voxels is nonzero only inside the cubes of two voxels'
    side around their centres; a pixel is kept when it lies within the projected radius of such
    a cube (the cube's circumscribed sphere, at the voxel's depth) of a projected hull centre.
    Conservative: a kept ray may still miss every cube (its operator row is then empty).
    """
    device = hull.device
    B = cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    out = torch.zeros(B, H * W, dtype=torch.bool, device=device)
    centers = grid.centers(device).reshape(-1, 3)[hull.reshape(-1)]
    if centers.shape[0] == 0:
        return out.reshape(B, H, W)
    radius_world = float(grid.voxel_size(device).norm())  # half-diagonal of the 2-voxel cube
    focal = float(cams.intrinsics[:, :2, :2].diagonal(dim1=-2, dim2=-1).abs().max())
    uv, depth = project_points(cams, centers)
    front = depth > 1e-9
    if not bool(front.any()):
        return out.reshape(B, H, W)
    r = math.ceil(focal * radius_world / float(depth[front].min())) + 1
    u, v = torch.floor(uv[..., 0]).long(), torch.floor(uv[..., 1]).long()
    for b in range(B):
        ok = front[b] & (u[b] >= -r) & (u[b] < W + r) & (v[b] >= -r) & (v[b] < H + r)
        hit = torch.zeros(H + 2 * r, W + 2 * r, device=device)
        hit[v[b][ok] + r, u[b][ok] + r] = 1.0
        grown = F.max_pool2d(hit[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]
        out[b] = grown[r:H + r, r:W + r].reshape(-1) > 0
    return out.reshape(B, H, W)
