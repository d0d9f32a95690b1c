"""The emission-only projector: a pixel is the line integral, in world units, of the
trilinearly interpolated density along its ray.

Rays are marched through the grid's box grown by half a voxel (the support of the trilinear
interpolant) in segments of ``step`` voxels; each segment contributes its length times the
density at its midpoint. Two backends share these samples and agree to float precision:

- matrix-free (:class:`MatrixFreeOperator`): ``grid_sample`` on the dense volume, autograd
  for the adjoint; differentiable, memory light, the renderer for full images;
- assembled (:class:`~flamerecon.sparse_ops.CsrOperator`): the same weights stored once as CSR,
  restricted to silhouette rays x hull voxels; fastest for repeated solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera

from .cameras import pixel_centers, pixel_rays
from .grid import VoxelGrid
from .sparse_ops import CsrOperator

#: samples per chunk when marching (bounds memory: about 100 bytes per sample and channel).
CHUNK_SAMPLES = 4_000_000


@dataclass
class Rays:
    """Flat ray batch: origins (R, 3), unit directions (R, 3), world units."""

    origins: torch.Tensor
    directions: torch.Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def __getitem__(self, idx) -> Rays:
        return Rays(self.origins[idx], self.directions[idx])

    def to(self, device) -> Rays:
        return Rays(self.origins.to(device), self.directions.to(device))


def camera_rays(cams: PinholeCamera, masks: torch.Tensor | None = None) -> tuple[Rays, torch.Tensor]:
    """Rays through pixel centres of every camera, row-major per image, cameras in order.

    With ``masks`` (B, H, W) bool only the masked pixels are kept. Returns the rays and the
    flat pixel index ``b * H * W + v * W + u`` (R,) of each ray.
    """
    B = cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    device = cams.intrinsics.device
    uv = pixel_centers(H, W, device=device)[None].expand(B, -1, -1).contiguous()
    origins, dirs = pixel_rays(cams, uv)
    flat = torch.arange(B * H * W, device=device)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    if masks is not None:
        keep = masks.reshape(-1).to(device)
        origins, dirs, flat = origins[keep], dirs[keep], flat[keep]
    return Rays(origins, dirs), flat


def march_box(grid: VoxelGrid, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The box rays are marched through: the grid's box grown by half a voxel, (3,), (3,)."""
    half = 0.5 * grid.voxel_size(device)
    return grid.lo(device) - half, grid.hi(device) + half


def ray_box(rays: Rays, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: entry and exit distances (R,), entry clamped at 0; exit <= entry means a miss."""
    d = rays.directions
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0 = (lo - rays.origins) / safe
    t1 = (hi - rays.origins) / safe
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


def ray_samples(rays: Rays, grid: VoxelGrid, step: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Segment midpoints (R, S, 3) and segment lengths (R, S) along each ray inside the
    march box; ``step`` is the segment length in units of the smallest voxel side."""
    lo, hi = march_box(grid, rays.origins.device)
    t_near, t_far = ray_box(rays, lo, hi)
    ds = float(step) * float(grid.voxel_size().min())
    span = (t_far - t_near).clamp_min(0.0)
    S = max(1, int(torch.ceil(span.max() / ds).item())) if len(rays) else 1
    start = t_near[:, None] + torch.arange(S, device=span.device, dtype=span.dtype) * ds
    length = (t_far[:, None] - start).clamp(0.0, ds)
    mid = start + 0.5 * length
    points = rays.origins[:, None, :] + mid[..., None] * rays.directions[:, None, :]
    return points, length


def _chunks(rays: Rays, grid: VoxelGrid, step: float):
    """Yield (slice, rays) chunks small enough to march at once."""
    diag = float(torch.linalg.norm(grid.hi() - grid.lo() + grid.voxel_size()))
    per_ray = max(1, int(diag / (float(step) * float(grid.voxel_size().min()))) + 1)
    size = max(1, CHUNK_SAMPLES // per_ray)
    for s in range(0, len(rays), size):
        sl = slice(s, min(s + size, len(rays)))
        yield sl, rays[sl]


def integrate_dense(volume: torch.Tensor, grid: VoxelGrid, rays: Rays, step: float = 0.5) -> torch.Tensor:
    """Line integrals (R, C) of a dense volume (C, nz, ny, nx) along ``rays``; differentiable."""
    C = volume.shape[0]
    out = []
    for _, chunk in _chunks(rays, grid, step):
        points, length = ray_samples(chunk, grid, step)
        coords = grid.world_to_normalized(points)  # (R, S, 3) as x, y, z
        vals = F.grid_sample(
            volume[None], coords[None, None], mode="bilinear", padding_mode="zeros", align_corners=False
        )  # (1, C, 1, R, S)
        out.append((vals[0, :, 0] * length[None]).sum(-1).T)
    if not out:
        return volume.new_zeros(0, C)
    return torch.cat(out, 0)


def trilinear_weights(
    points: torch.Tensor, length: torch.Tensor, grid: VoxelGrid
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat voxel indices (P, 8) and weights (P, 8) of the 8 trilinear corners of each of the
    P samples ``points`` (P, 3), weights scaled by segment ``length`` (P,); corners outside
    the grid get weight 0 and index 0 (``grid_sample``'s zero padding)."""
    u = grid.world_to_index(points)
    i0 = torch.floor(u)
    f = u - i0
    i0 = i0.long()
    corner = i0[:, None, :] + torch.tensor([0, 1], device=u.device)[None, :, None]  # (P, 2, 3)
    frac = torch.stack([1 - f, f], dim=1)  # (P, 2, 3) weight of corner 0 / 1 per axis
    size = torch.tensor(grid.resolution, device=u.device)
    inside = (corner >= 0) & (corner < size)
    frac = frac * inside
    corner = corner.clamp_min(0).minimum(size - 1)
    nx, ny, _ = grid.resolution
    w = (
        frac[:, :, None, None, 2] * frac[:, None, :, None, 1] * frac[:, None, None, :, 0]
    ).reshape(-1, 8) * length[:, None]
    idx = (
        (corner[:, :, None, None, 2] * ny + corner[:, None, :, None, 1]) * nx
        + corner[:, None, None, :, 0]
    ).reshape(-1, 8)
    return idx, w


def assemble(
    grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
) -> CsrOperator:
    """The operator rays x voxels (N, M) as CSR; column m is grid voxel ``voxel_index[m]``.

    Only columns in ``voxel_index`` (the hull) are kept; rows are the rays in order.
    """
    device = rays.origins.device
    column = torch.full((grid.num_voxels,), -1, dtype=torch.long, device=device)
    column[voxel_index.to(device)] = torch.arange(voxel_index.numel(), device=device)
    M = int(voxel_index.numel())
    rows_all, cols_all, vals_all = [], [], []
    for sl, chunk in _chunks(rays, grid, step):
        points, length = ray_samples(chunk, grid, step)
        valid = length > 0
        row = torch.arange(sl.start, sl.start + len(chunk), device=device)[:, None].expand_as(length)[valid]
        idx, w = trilinear_weights(points[valid], length[valid], grid)
        col = column[idx]
        keep = (col >= 0) & (w > 0)
        key = ((row[:, None] - sl.start) * M + col)[keep]
        # merge duplicates (neighbouring samples share corners) within the chunk
        key, order = torch.sort(key)
        key, counts = torch.unique_consecutive(key, return_counts=True)
        seg = torch.repeat_interleave(torch.arange(key.numel(), device=device), counts)
        val = torch.zeros(key.numel(), dtype=w.dtype, device=device).index_add_(0, seg, w[keep][order])
        rows_all.append(key // M + sl.start)
        cols_all.append(key % M)
        vals_all.append(val)
    if rows_all:
        rows, cols, vals = torch.cat(rows_all), torch.cat(cols_all), torch.cat(vals_all)
    else:
        rows = cols = torch.zeros(0, dtype=torch.long, device=device)
        vals = torch.zeros(0, device=device)
    return CsrOperator.from_sorted_coo(rows, cols, vals, (len(rays), M))


class MatrixFreeOperator:
    """Rays x hull voxels without storing weights: scatter into the grid, ``grid_sample``.

    ``forward`` (M, C) -> (N, C) is differentiable; ``adjoint`` is its vector-Jacobian product.
    """

    def __init__(self, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5):
        self.grid, self.rays, self.step = grid, rays, float(step)
        self.voxel_index = voxel_index.to(rays.origins.device)
        self.shape = (len(rays), int(voxel_index.numel()))

    def volume(self, x: torch.Tensor) -> torch.Tensor:
        """Scatter hull values (M, C) into a dense volume (C, nz, ny, nx)."""
        C = x.shape[1]
        vol = x.new_zeros(C, self.grid.num_voxels)
        vol = vol.index_copy(1, self.voxel_index, x.T)
        return vol.reshape(C, *self.grid.shape)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return integrate_dense(self.volume(x), self.grid, self.rays, self.step)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        x = torch.zeros(self.shape[1], y.shape[1], dtype=y.dtype, device=y.device, requires_grad=True)
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(self.forward(x), x, grad_outputs=y)
        return grad


def render_image(
    volume: torch.Tensor, grid: VoxelGrid, cams: PinholeCamera, step: float = 0.5
) -> torch.Tensor:
    """Render every pixel of every camera: volume (C, nz, ny, nx) -> images (B, C, H, W)."""
    B = cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    rays, _ = camera_rays(cams)
    with torch.no_grad():
        pix = integrate_dense(volume, grid, rays.to(volume.device), step)
    return pix.T.reshape(volume.shape[0], B, H, W).transpose(0, 1).contiguous()


def make_operator(
    backend: str, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
):
    """Build the ``assembled`` (CSR) or ``matrix_free`` operator for rays x hull voxels."""
    if backend == "assembled":
        return assemble(grid, rays, voxel_index, step)
    if backend == "matrix_free":
        return MatrixFreeOperator(grid, rays, voxel_index, step)
    raise ValueError(f"projector.backend: unknown backend '{backend}'; use 'assembled' or 'matrix_free'")
