"""An assembled linear operator: A (N, M) as a torch CSR matrix with int32 indices, plus A^T.

Keeping A^T as its own CSR makes the adjoint a row-parallel product as fast as the forward
one, at the cost of storing the values twice.
"""

from __future__ import annotations

import warnings

import torch

warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")


def _csr32(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> torch.Tensor:
    return torch.sparse_csr_tensor(crow.to(torch.int32), col.to(torch.int32), val, size=shape)


class _CsrMatmul(torch.autograd.Function):
    """y = A x with dL/dx = A^T dL/dy, using the stored transpose (no transpose at run time)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, A: torch.Tensor, AT: torch.Tensor) -> torch.Tensor:
        ctx.AT = AT
        return A @ x

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        return ctx.AT @ grad_out.contiguous(), None, None


class CsrOperator:
    """A stored once as CSR and once transposed; ``forward`` computes A x, ``adjoint`` A^T y.

    ``x`` is (M, C) and ``y`` (N, C), float32 on the operator's device.
    """

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]):
        """Build from COO triplets (duplicates are summed)."""
        N, M = int(shape[0]), int(shape[1])
        self.shape = (N, M)
        coo = torch.sparse_coo_tensor(torch.stack([rows.long(), cols.long()]), values, (N, M)).coalesce()
        csr = coo.to_sparse_csr()
        self.A = _csr32(csr.crow_indices(), csr.col_indices(), csr.values(), (N, M))
        csc = coo.to_sparse_csc()  # the CSC of A is the CSR of A^T
        self.AT = _csr32(csc.ccol_indices(), csc.row_indices(), csc.values(), (M, N))

    @property
    def nnz(self) -> int:
        return int(self.A.values().numel())

    @property
    def device(self) -> torch.device:
        return self.A.device

    def nbytes(self) -> int:
        """Bytes of one copy of A (values + column indices + row pointers)."""
        return self.nnz * (self.A.values().element_size() + 4) + (self.shape[0] + 1) * 4

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """A x for x (M, C) -> (N, C); differentiable in ``x`` (the backward is A^T)."""
        if x.requires_grad and torch.is_grad_enabled():
            return _CsrMatmul.apply(x, self.A, self.AT)
        return self.A @ x

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.AT @ y

    def to(self, device) -> CsrOperator:
        out = object.__new__(CsrOperator)
        out.shape = self.shape
        out.A = self.A.to(device)
        out.AT = self.AT.to(device)
        return out

    def to_scipy(self):
        """A as ``scipy.sparse.csr_matrix`` (float32), for peers and dumps."""
        import scipy.sparse as sp

        A = self.A.cpu()
        return sp.csr_matrix(
            (A.values().numpy(), A.col_indices().numpy(), A.crow_indices().numpy()), shape=self.shape
        )
