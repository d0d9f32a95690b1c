"""Finite differences between neighbouring hull voxels, and an operator that stacks them
under the projector so a gradient-L2 penalty becomes part of a least-squares data term."""

from __future__ import annotations

import torch

from flamerecon.operators.base import LinearOperator
from flamerecon.operators.sparse import CsrOperator


def forward_neighbours(grid_shape: tuple[int, int, int], voxel_index: torch.Tensor) -> torch.Tensor:
    """For each hull voxel, the column of its neighbour one cell further along x, y and z:
    (3, M) long, -1 where that cell is outside the grid or the hull.

    ``grid_shape`` is (nz, ny, nx); ``voxel_index`` (M,) long flat indices, x fastest.
    """
    nz, ny, nx = (int(n) for n in grid_shape)
    device = voxel_index.device
    flat = voxel_index.long()
    M = int(flat.numel())
    column = torch.full((nz * ny * nx,), -1, dtype=torch.long, device=device)
    column[flat] = torch.arange(M, device=device)
    k, rest = flat // (ny * nx), flat % (ny * nx)
    j, i = rest // nx, rest % nx
    out = torch.full((3, M), -1, dtype=torch.long, device=device)
    for axis, (coord, size, stride) in enumerate(((i, nx, 1), (j, ny, nx), (k, nz, ny * nx))):
        inside = coord + 1 < size
        out[axis, inside] = column[flat[inside] + stride]
    return out


def hull_gradient(grid_shape: tuple[int, int, int], voxel_index: torch.Tensor) -> CsrOperator:
    """Forward differences D (E, M) along x, y and z between pairs of hull voxels that are
    neighbours in the grid; row e is ``x[j] - x[i]``. Pairs with a voxel outside the hull
    are left out (no penalty across the hull boundary).

    ``grid_shape`` is (nz, ny, nx); ``voxel_index`` (M,) long flat indices, x fastest.
    """
    device = voxel_index.device
    M = int(voxel_index.numel())
    nb = forward_neighbours(grid_shape, voxel_index)
    here = torch.arange(M, device=device)
    pairs = [torch.stack([here[nb[a] >= 0], nb[a][nb[a] >= 0]]) for a in range(3)]
    i, j = torch.cat(pairs, 1)
    E = int(i.numel())
    rows = torch.arange(E, device=device).repeat(2)
    cols = torch.cat([j, i])
    values = torch.cat([torch.ones(E, device=device), -torch.ones(E, device=device)])
    return CsrOperator.from_coo(rows, cols, values, (E, M))


class StackedOperator:
    """[A; weight * D] (N + E, M): forward concatenates, adjoint sums the two back-projections."""

    def __init__(self, A: LinearOperator, D: LinearOperator, weight: float) -> None:
        if A.shape[1] != D.shape[1]:
            raise ValueError(f"operators disagree on unknowns: {A.shape} vs {D.shape}")
        self.A, self.D, self.weight = A, D, float(weight)
        self.shape = (A.shape[0] + D.shape[0], A.shape[1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.A.forward(x), self.weight * self.D.forward(x)])

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        N = self.A.shape[0]
        return self.A.adjoint(y[:N]) + self.weight * self.D.adjoint(y[N:].contiguous())


class HullGradient:
    """The 3D forward-difference gradient on the hull, grouped per voxel for isotropic TV.

    ``forward`` maps densities (M, C) to differences (3, M, C): entry (a, m) is the density of
    the neighbour of voxel m one cell further along axis a (x, y, z) minus that of m, and 0
    where that neighbour is outside the grid or the hull (no difference across the hull
    boundary). ``adjoint`` maps (3, M, C) back to (M, C). ``norm_sq_bound`` = 12 >= ||D||^2:
    D^T D is a graph Laplacian of maximum degree 6, whose norm is at most 2 * 6. ``shape`` is
    that of D as a matrix, (3 M, M).
    """

    norm_sq_bound = 12.0

    def __init__(self, grid_shape: tuple[int, int, int], voxel_index: torch.Tensor) -> None:
        nb = forward_neighbours(grid_shape, voxel_index)
        self.M = int(voxel_index.numel())
        self.shape = (3 * self.M, self.M)
        self.here = [(nb[a] >= 0).nonzero().squeeze(1) for a in range(3)]
        self.there = [nb[a][h] for a, h in enumerate(self.here)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = x.new_zeros(3, *x.shape)
        for a in range(3):
            d[a, self.here[a]] = x[self.there[a]] - x[self.here[a]]
        return d

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        out = y.new_zeros(y.shape[1:])
        for a in range(3):
            ya = y[a, self.here[a]]
            out.index_add_(0, self.there[a], ya).index_add_(0, self.here[a], -ya)
        return out
