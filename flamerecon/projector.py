"""The emission-only projector: a pixel is the line integral, in world units, of the
trilinearly interpolated density along its ray.

Rays are marched through the grid's box grown by half a voxel (the support of the trilinear
interpolant) in segments of ``step`` voxels; each segment contributes its length times the
density at its midpoint. Two backends share these samples and agree to float precision:

- matrix-free (:class:`MatrixFreeOperator`): ``grid_sample`` on the dense volume, autograd
  for the adjoint; differentiable, memory light, the renderer for full images;
- assembled (:class:`~flamerecon.operators.CsrOperator`): the same weights stored once as CSR,
  restricted to silhouette rays x hull voxels; fastest for repeated solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.geometry.camera import PinholeCamera

from .cameras import pixel_centers, pixel_rays
from .grid import VoxelGrid
from .operators.sparse import CsrOperator

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


def support_box(grid: VoxelGrid, voxel_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The box (3,), (3,) outside which the trilinear interpolant of values on the voxels
    ``voxel_index`` (flat indices) vanishes: their centres' bounding box grown by a voxel."""
    nx, ny, _ = grid.resolution
    device = voxel_index.device
    if voxel_index.numel() == 0:
        return grid.lo(device), grid.lo(device)
    ijk = torch.stack([voxel_index % nx, (voxel_index // nx) % ny, voxel_index // (nx * ny)], -1)
    size = grid.voxel_size(device)
    lo = grid.lo(device) + (ijk.amin(0) - 0.5) * size
    hi = grid.lo(device) + (ijk.amax(0) + 1.5) * size
    return lo, hi


def ray_samples(
    rays: Rays, grid: VoxelGrid, step: float, box: tuple[torch.Tensor, torch.Tensor] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Segment midpoints (R, S, 3) and segment lengths (R, S) along each ray through the
    march box; ``step`` is the segment length in units of the smallest voxel side.

    Segments always start at the march box's entry, so that narrowing to ``box`` (where the
    density can be nonzero, see :func:`support_box`) only skips segments outside it and
    leaves every other sample where the full march puts it.
    """
    lo, hi = march_box(grid, rays.origins.device)
    t_near, t_far = ray_box(rays, lo, hi)
    ds = float(step) * float(grid.voxel_size().min())
    first = torch.zeros_like(t_near)
    end = torch.ceil((t_far - t_near).clamp_min(0.0) / ds)
    if box is not None:
        b_near, b_far = ray_box(rays, *box)
        first = torch.floor((b_near - t_near).clamp_min(0.0) / ds)
        end = torch.minimum(end, torch.ceil((b_far - t_near).clamp_min(0.0) / ds))
        end = torch.where(b_far > b_near, end, first)
    count = (end - first).clamp_min(0.0)
    S = max(1, int(count.max().item())) if len(rays) else 1
    k = first[:, None] + torch.arange(S, device=t_near.device, dtype=t_near.dtype)
    start = t_near[:, None] + k * ds
    length = (t_far[:, None] - start).clamp(0.0, ds) * (k < end[:, None])
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


def integrate_dense(
    volume: torch.Tensor, grid: VoxelGrid, rays: Rays, step: float = 0.5,
    box: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Line integrals (R, C) of a dense volume (C, nz, ny, nx) along ``rays``; differentiable.
    ``box`` may narrow the march to where the volume can be nonzero (see :func:`support_box`)."""
    C = volume.shape[0]
    out = []
    for _, chunk in _chunks(rays, grid, step):
        points, length = ray_samples(chunk, grid, step, box)
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


def cells_touching(grid: VoxelGrid, voxel_index: torch.Tensor) -> torch.Tensor:
    """(nz+1, ny+1, nx+1) bool: entry [k+1, j+1, i+1] says whether the trilinear cell with lower
    corner (i, j, k), i in -1..nx-1, has one of ``voxel_index``'s voxels among its 8 corners."""
    nx, ny, nz = grid.resolution
    occupied = torch.zeros(grid.num_voxels, device=voxel_index.device)
    occupied[voxel_index] = 1.0
    padded = F.pad(occupied.view(1, 1, nz, ny, nx), (1, 1, 1, 1, 1, 1))
    return F.max_pool3d(padded, 2, stride=1)[0, 0] > 0


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
    box = support_box(grid, voxel_index.to(device))
    live = cells_touching(grid, voxel_index.to(device))
    top = torch.tensor(live.shape[::-1], device=device) - 1  # (nx, ny, nz)
    rows_all, cols_all, vals_all = [], [], []
    for sl, chunk in _chunks(rays, grid, step):
        points, length = ray_samples(chunk, grid, step, box)
        valid = length > 0
        # keep only samples whose trilinear cell touches the hull (most of the support box
        # does not): the 8-corner work below is then done for samples that contribute
        cell = (torch.floor(grid.world_to_index(points)).long() + 1).clamp_min_(0).minimum(top)
        valid &= live[cell[..., 2], cell[..., 1], cell[..., 0]]
        row = torch.arange(sl.start, sl.start + len(chunk), device=device)[:, None].expand_as(length)[valid]
        idx, w = trilinear_weights(points[valid], length[valid], grid)
        col = column[idx]
        keep = (col >= 0) & (w > 0)
        key = ((row[:, None] - sl.start) * M + col)[keep]
        # merge duplicates (neighbouring samples share corners) within the chunk
        key, order = torch.sort(key, stable=True)  # duplicates summed in ray order: reproducible
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


#: nonzeros of the assembled operator per ray sample inside the hull's support box. Measured on
#: the synthetic scene: 1.51 (16^3 grid, 48x36 images), 1.09 (32^3, 160x120), 0.91 (64^3,
#: 320x240), 0.82 (128^3, 320x240): neighbouring samples share corners, and support-box samples
#: outside the hull add none. 1.0 is within 0.7x-1.2x of the truth there, high for large grids.
NNZ_PER_SAMPLE = 1.0
#: bytes of temporaries per ray sample of one chunk while assembling (points, 8 corner indices
#: and weights, column lookup, sort keys). With the two constants below the peak estimate was
#: 0.8x (16^3, 43 MB measured) to 1.7x (128^3, 1.26 GB measured) the peak RSS growth.
BYTES_PER_CHUNK_SAMPLE = 450
#: bytes per nonzero at the end of assembly: COO triplets (int64 row and column, float32 value)
#: concatenated, the CSR copies of A and A^T (int32 column + float32 value each) and the sort.
BYTES_PER_NNZ_PEAK = 80


@dataclass
class OperatorMemory:
    """Estimated size of the assembled operator: nonzeros, bytes kept (A and A^T), peak bytes."""

    nnz: int
    operator_bytes: int
    peak_bytes: int


def assembled_memory(
    grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5
) -> OperatorMemory:
    """Estimate, without assembling, what :func:`assemble` would store and its peak memory.

    Counts the ray samples inside the hull's support box (a slab test per ray, O(rays)); the
    nonzeros are ``NNZ_PER_SAMPLE`` per sample, stored twice (A and A^T) at 8 bytes each.
    """
    device = rays.origins.device
    N, M = len(rays), int(voxel_index.numel())
    if N == 0 or M == 0:
        return OperatorMemory(0, 4 * (N + M + 2), 4 * (N + M + 2))
    box = support_box(grid, voxel_index.to(device))
    ds = float(step) * float(grid.voxel_size().min())
    per_ray = torch.cat([
        ((t_far - t_near).clamp_min(0.0) / ds).ceil()
        for t_near, t_far in (ray_box(chunk, *box) for _, chunk in _chunks(rays, grid, step))
    ])
    chunk_samples = max(float(per_ray[sl].sum()) for sl, _ in _chunks(rays, grid, step))
    nnz = int(float(per_ray.sum()) * NNZ_PER_SAMPLE)
    operator_bytes = 2 * 8 * nnz + 4 * (N + M + 2)
    peak = operator_bytes + BYTES_PER_NNZ_PEAK * nnz + int(BYTES_PER_CHUNK_SAMPLE * chunk_samples)
    return OperatorMemory(nnz, operator_bytes, peak)


class MatrixFreeOperator:
    """Rays x hull voxels without storing weights: scatter into the grid, ``grid_sample``.

    ``forward`` (M, C) -> (N, C) is differentiable; ``adjoint`` is its vector-Jacobian product.
    """

    def __init__(self, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float = 0.5):
        self.grid, self.rays, self.step = grid, rays, float(step)
        self.voxel_index = voxel_index.to(rays.origins.device)
        self.box = support_box(grid, self.voxel_index)
        self.shape = (len(rays), int(voxel_index.numel()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return integrate_dense(self.grid.dense(x, self.voxel_index), self.grid, self.rays, self.step, self.box)

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
