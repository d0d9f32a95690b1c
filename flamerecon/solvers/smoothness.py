"""Finite differences between neighbouring hull voxels, and an operator that stacks them
under the projector so a gradient-L2 penalty becomes part of a least-squares data term."""

from __future__ import annotations

import torch

from ..sparse_ops import CsrOperator
from .base import LinearOperator


def hull_gradient(grid_shape: tuple[int, int, int], voxel_index: torch.Tensor) -> CsrOperator:
    """Forward differences D (E, M) along x, y and z between pairs of hull voxels that are
    neighbours in the grid; row e is ``x[j] - x[i]``. Pairs with a voxel outside the hull
    are left out (no penalty across the hull boundary).

    ``grid_shape`` is (nz, ny, nx); ``voxel_index`` (M,) long flat indices, x fastest.
    """
    nz, ny, nx = (int(n) for n in grid_shape)
    device = voxel_index.device
    M = int(voxel_index.numel())
    column = torch.full((nz * ny * nx,), -1, dtype=torch.long, device=device)
    column[voxel_index.long()] = torch.arange(M, device=device)
    column = column.view(nz, ny, nx)
    pairs = []
    for axis in range(3):
        n = column.shape[axis]
        lo = column.narrow(axis, 0, n - 1).reshape(-1)
        hi = column.narrow(axis, 1, n - 1).reshape(-1)
        keep = (lo >= 0) & (hi >= 0)
        pairs.append(torch.stack([lo[keep], hi[keep]]))
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
