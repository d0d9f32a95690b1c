"""Motion on the voxel grid: a smooth displacement field, the trilinear warp it defines (dense
and differentiable, or as a sparse matrix between two hulls), and the operators that view one
frame's density through a neighbouring frame's cameras.

A displacement ``u`` (3, nz, ny, nx) in cells, components (dx, dy, dz), is given on the grid of
the frame the density is carried *to*: the warped density is

    (W_u x)(p) = x(p - u(p)),

trilinear in x (zero outside the grid), i.e. a backward warp, which is linear in x with eight
weights per output cell. Its dense form (:func:`warp_volume`, ``grid_sample`` with
``align_corners=True``) is differentiable in ``u`` and is what a motion is fitted through; its
matrix form (:func:`warp_matrix`, rows on one hull, columns on another) is what a solve uses,
with the exact adjoint of a stored transpose.

A velocity is the same field read as cells per frame: :func:`advect_volume` carries a density
``steps`` frames along a steady one (semi-Lagrangian: the characteristic traced back ``steps``
times through ``u``, then the density interpolated once, so a long horizon is not blurred by
repeated interpolation); :func:`divergence` and :func:`curl` differentiate it (central
differences, one-sided at the border, ``torch.gradient``). :func:`sample_points` reads a field
at scattered cell coordinates, which is how a fit evaluates only the cells it needs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from flamerecon.operators.base import LinearOperator
from flamerecon.operators.sparse import CsrOperator


def upsample_displacement(control: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    """A displacement on a coarse control grid (3, gz, gy, gx) -> (3, nz, ny, nx), trilinear with
    the corner cells aligned (a constant field stays constant); values are cells of the fine
    grid either way."""
    if tuple(control.shape[1:]) == tuple(shape):
        return control
    return F.interpolate(control[None], size=tuple(shape), mode="trilinear", align_corners=True)[0]


def _sample_grid(u: torch.Tensor) -> torch.Tensor:
    """grid_sample's (1, nz, ny, nx, 3) normalised coordinates of p - u(p)."""
    _, nz, ny, nx = u.shape
    axes = [torch.arange(n, device=u.device, dtype=u.dtype) for n in (nz, ny, nx)]
    k, j, i = torch.meshgrid(*axes, indexing="ij")
    coords = []
    for pos, comp, n in ((i, u[0], nx), (j, u[1], ny), (k, u[2], nz)):
        coords.append((pos - comp) * (2.0 / max(n - 1, 1)) - 1.0)
    return torch.stack(coords, -1)[None]


def warp_volume(volume: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """W_u applied to a dense density (C, nz, ny, nx) (module doc); differentiable in both."""
    grid = _sample_grid(u.to(volume.dtype))
    return F.grid_sample(volume[None], grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0]


def cell_points(flat_index: torch.Tensor, shape: tuple[int, int, int], dtype=torch.float64) -> torch.Tensor:
    """(3, P) cell coordinates (x, y, z) of the flat indices (P,) of a grid of ``shape`` (nz, ny, nx)."""
    _, ny, nx = (int(n) for n in shape)
    flat = flat_index.long()
    return torch.stack([flat % nx, (flat // nx) % ny, flat // (ny * nx)]).to(dtype)


def sample_points(field: torch.Tensor, points: torch.Tensor, padding: str = "zeros") -> torch.Tensor:
    """A field (C, nz, ny, nx) read trilinearly at ``points`` (3, P) in its own cell
    coordinates (x, y, z; cell centres at integers): (C, P), differentiable in both.
    ``padding``: ``zeros`` outside the grid (a density) or ``border`` (a velocity extends)."""
    nz, ny, nx = field.shape[1:]
    scale = [2.0 / max(n - 1, 1) for n in (nx, ny, nz)]
    grid = torch.stack([points[a].to(field.dtype) * scale[a] - 1.0 for a in range(3)], -1)
    return F.grid_sample(field[None], grid.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode=padding,
                         align_corners=True).reshape(field.shape[0], -1)


def advect_volume(volume: torch.Tensor, u: torch.Tensor, steps: int) -> torch.Tensor:
    """A density (C, nz, ny, nx) carried ``steps`` frames by the steady velocity ``u`` (3, nz,
    ny, nx) in cells per frame: each cell p traced back through p <- p - u(p) ``steps`` times
    (u read trilinearly, held at the border), the density then read once there (zero outside
    the grid). ``steps`` = 1 is :func:`warp_volume`; 0 returns ``volume``."""
    if steps == 0:
        return volume
    shape = tuple(int(n) for n in volume.shape[1:])
    points = cell_points(torch.arange(volume[0].numel(), device=volume.device), shape, u.dtype)
    for _ in range(int(steps)):
        points = points - sample_points(u, points, "border")
    return sample_points(volume, points).reshape(volume.shape)


def _derivative(component: torch.Tensor, axis: int, spacing: float) -> torch.Tensor:
    """d component / d (grid axis ``axis`` of (nz, ny, nx)); zero along an axis of one cell."""
    if component.shape[axis] < 2:
        return torch.zeros_like(component)
    return torch.gradient(component, spacing=float(spacing), dim=axis)[0]


def divergence(u: torch.Tensor, spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    """div u (nz, ny, nx) of a field (3, nz, ny, nx) with components (x, y, z), ``spacing`` its
    (x, y, z) cell size (in the units its values are divided by)."""
    return sum(_derivative(u[a], 2 - a, spacing[a]) for a in range(3))


def curl(u: torch.Tensor, spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    """The vorticity curl u (3, nz, ny, nx), components (x, y, z), of a field (3, nz, ny, nx)."""
    def d(comp: int, along: int) -> torch.Tensor:
        return _derivative(u[comp], 2 - along, spacing[along])

    return torch.stack([d(2, 1) - d(1, 2), d(0, 2) - d(2, 0), d(1, 0) - d(0, 1)])


def warp_matrix(u: torch.Tensor, src_index: torch.Tensor, dst_index: torch.Tensor) -> CsrOperator:
    """W_u as a sparse (M_dst, M_src) operator from the hull values of one frame
    (``src_index``, sorted flat indices of its hull) to those of another (``dst_index``):
    row r is cell dst_index[r] of the warped density; weights on cells outside the source hull
    (where its density is zero) or outside the grid are dropped. Equal to :func:`warp_volume`
    read at ``dst_index`` for a density that is zero off ``src_index``."""
    _, nz, ny, nx = u.shape
    dev = src_index.device
    dst = dst_index.to(dev)
    k, j, i = dst // (ny * nx), (dst // nx) % ny, dst % nx
    flat_u = u.reshape(3, -1).to(dev, torch.float64)[:, dst]
    q = torch.stack([i - flat_u[0], j - flat_u[1], k - flat_u[2]])  # source point (x, y, z) in cells
    base = q.floor()
    frac = q - base
    base = base.long()
    lookup = torch.full((nz * ny * nx,), -1, dtype=torch.long, device=dev)
    lookup[src_index] = torch.arange(src_index.numel(), device=dev)
    rows, cols, vals = [], [], []
    row = torch.arange(dst.numel(), device=dev)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                ci, cj, ck = base[0] + dx, base[1] + dy, base[2] + dz
                w = ((frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1])
                     * (frac[2] if dz else 1 - frac[2]))
                inside = (ci >= 0) & (ci < nx) & (cj >= 0) & (cj < ny) & (ck >= 0) & (ck < nz) & (w > 0)
                flat = (ck * ny + cj) * nx + ci
                col = torch.where(inside, lookup[flat.clamp(0, nz * ny * nx - 1)], -1)
                keep = col >= 0
                rows.append(row[keep])
                cols.append(col[keep])
                vals.append(w[keep])
    rows_t, cols_t, vals_t = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    return CsrOperator.from_coo(rows_t, cols_t, vals_t.float(), (int(dst.numel()), int(src_index.numel())))


class ComposedOperator:
    """weight * A W (N, M_src): a frame's projector A (N, M_dst) viewing a density carried onto
    its hull by W (M_dst, M_src); the adjoint is weight * W^T A^T."""

    def __init__(self, A: LinearOperator, W: LinearOperator, weight: float = 1.0) -> None:
        if A.shape[1] != W.shape[0]:
            raise ValueError(f"operators disagree: A {tuple(A.shape)} after W {tuple(W.shape)}")
        self.A, self.W, self.weight = A, W, float(weight)
        self.shape = (int(A.shape[0]), int(W.shape[1]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.weight * self.A.forward(self.W.forward(x))

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.weight * self.W.adjoint(self.A.adjoint(y))


class RowStack:
    """Operators on the same unknowns stacked by rows, [B_1; B_2; ...]: forward concatenates,
    the adjoint sums the back-projections of each block."""

    def __init__(self, blocks: list[LinearOperator]) -> None:
        if not blocks or len({int(b.shape[1]) for b in blocks}) != 1:
            raise ValueError(f"blocks must share their unknowns, got {[tuple(b.shape) for b in blocks]}")
        self.blocks = blocks
        self.sizes = [int(b.shape[0]) for b in blocks]
        self.shape = (sum(self.sizes), int(blocks[0].shape[1]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([b.forward(x) for b in self.blocks])

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        parts = torch.split(y, self.sizes)
        out = self.blocks[0].adjoint(parts[0].contiguous())
        for b, part in zip(self.blocks[1:], parts[1:]):
            out = out + b.adjoint(part.contiguous())
        return out
