"""The assembled linear operator: A (N, M) as a torch CSR matrix with int32 indices, and A^T
where the adjoint needs it.

On the CPU the compiled adjoint (:mod:`~flamerecon.operators.compiled`) reads A's rows, so A
is stored once. Elsewhere A^T is kept as its own CSR, which makes the adjoint a row-parallel
product as fast as the forward one, at the cost of storing the values twice. On CUDA a product with C columns runs as C
sparse matrix-vector products: cuSPARSE's SpMM with three row-major columns measured 3-4.5x
slower than three SpMVs on an H100 (0.43 vs 0.14 ms at 9.2 M nonzeros); on the CPU the
one SpMM is the faster (MKL reads A once for all columns).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from flamerecon.operators import compiled

warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")


def index_dtype(nnz: int) -> torch.dtype:
    """The index type of a CSR matrix with ``nnz`` entries: int32 (half the bytes; MKL and
    cuSPARSE take it) below 2^31 entries, else int64."""
    return torch.int32 if nnz < 2**31 else torch.long


def _csr(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> torch.Tensor:
    dtype = index_dtype(int(val.numel()))
    return torch.sparse_csr_tensor(crow.to(dtype), col.to(dtype), val, size=shape)


class GrowingArray:
    """A 1-D tensor appended to piece by piece without a second copy of it at any time.

    On the CPU the pieces go into a NumPy array that grows by half its size in place
    (``ndarray.resize``: ``realloc``, which moves the pages of a large block without copying
    them); a list of pieces concatenated at the end would need the pieces and the result at
    once, and freed pieces stay resident in the allocator's heap. Elsewhere (CUDA) the pieces
    are concatenated at the end."""

    def __init__(self, dtype: torch.dtype, device: torch.device):
        self.device = torch.device(device)
        self.size = 0
        self.pieces: list[torch.Tensor] = []
        self.array = np.empty(0, torch.empty(0, dtype=dtype).numpy().dtype) if self.device.type == "cpu" else None

    def append(self, piece: torch.Tensor) -> None:
        if self.array is None:
            self.pieces.append(piece)
        else:
            n = int(piece.numel())
            if self.size + n > self.array.size:
                self.array.resize(max(self.size + n, self.array.size * 3 // 2, 1 << 16), refcheck=False)
            self.array[self.size:self.size + n] = piece.numpy()
        self.size += int(piece.numel())

    def tensor(self) -> torch.Tensor:
        """The appended values (size,); the buffer is handed over (append no more)."""
        if self.array is None:
            out = torch.cat(self.pieces) if self.pieces else torch.zeros(0, device=self.device)
            self.pieces = []
            return out
        self.array.resize(self.size, refcheck=False)
        out, self.array = torch.from_numpy(self.array), None
        return out


#: entries per block when a transpose is built (:func:`transpose_csr`): its temporaries are
#: about 40 bytes per entry of a block
TRANSPOSE_BLOCK = 4_000_000


def transpose_csr(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, n_cols: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The CSR arrays of A^T from those of A (N, ``n_cols``): column pointers (n_cols + 1,),
    row indices and values (nnz,), rows ascending within each column, in A's index type.

    A counting sort over blocks of A's rows (about :data:`TRANSPOSE_BLOCK` entries each): each
    block's entries are sorted by column (stable, so rows stay ascending) and written after the
    earlier blocks' entries of the same column. Memory: the result plus one block's
    temporaries, never a second copy of A."""
    device, nnz = val.device, int(val.numel())
    dtype = index_dtype(nnz)
    N = int(crow.numel()) - 1
    counts = torch.bincount(col, minlength=n_cols) if nnz else torch.zeros(n_cols, dtype=torch.long, device=device)
    ccol = torch.zeros(n_cols + 1, dtype=torch.long, device=device)
    torch.cumsum(counts, 0, out=ccol[1:])
    free = ccol[:-1].clone()  # the next slot of each column
    row_t = torch.empty(nnz, dtype=dtype, device=device)
    val_t = torch.empty_like(val)
    crow_l = crow.long()
    r0 = 0
    while r0 < N:
        e0 = int(crow_l[r0])
        r1 = int(torch.searchsorted(crow_l, e0 + TRANSPOSE_BLOCK, right=True)) - 1
        r1 = min(N, max(r1, r0 + 1))
        e1 = int(crow_l[r1])
        c = col[e0:e1].long()
        cs, order = torch.sort(c, stable=True)
        here = torch.bincount(c, minlength=n_cols)
        first = torch.cumsum(here, 0) - here  # each column's first place in the block's order
        rank = torch.arange(e1 - e0, device=device) - first.index_select(0, cs)
        slot = free.index_select(0, cs) + rank
        rows = torch.repeat_interleave(torch.arange(r0, r1, device=device, dtype=dtype), crow_l[r0 + 1:r1 + 1] -
                                       crow_l[r0:r1])
        row_t[slot] = rows.index_select(0, order)
        val_t[slot] = val[e0:e1].index_select(0, order)
        free += here
        r0 = r1
    return ccol.to(dtype), row_t, val_t


def stable_argsort(keys: torch.Tensor) -> torch.Tensor:
    """The stable ascending order (n,) long of nonnegative integer ``keys`` (n,).

    On the CPU NumPy's stable sort (radix below 2^16, else a merge sort that uses the runs of
    nearly sorted keys) measured 2-5x faster than ``torch.sort(stable=True)`` (2.13, 2 threads).
    """
    if keys.is_cuda or keys.numel() == 0:
        return torch.argsort(keys, stable=True)
    top = int(keys.max())
    dtype = np.uint16 if top < 2**16 else np.int32 if top < 2**31 else np.int64
    return torch.from_numpy(np.argsort(keys.numpy().astype(dtype, copy=False), kind="stable"))


def csr_matmul(A: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """A (R, K) CSR times dense x (K, C) -> (R, C), by the faster kernel for the device."""
    if x.is_cuda and x.shape[1] > 1:
        return torch.stack([torch.mv(A, column) for column in x.t().contiguous()], 1)
    return A @ x


class _CsrMatmul(torch.autograd.Function):
    """y = A x with dL/dx = A^T dL/dy, by the operator's adjoint."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, op: CsrOperator) -> torch.Tensor:
        ctx.op = op
        return csr_matmul(op.A, x)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        return ctx.op.adjoint(grad_out.contiguous()), None


class CsrOperator:
    """A stored once as CSR; ``forward`` computes A x, ``adjoint`` A^T y.

    ``x`` is (M, C) and ``y`` (N, C), float32 on the operator's device. On the CPU with the
    compiled kernels (:mod:`~flamerecon.operators.compiled`) the adjoint reads A's rows;
    elsewhere A^T is stored too, transposed on first use (:attr:`AT`).
    """

    def __init__(self, A: torch.Tensor, AT: torch.Tensor | None = None):
        """Wrap a CSR matrix A (N, M) (int32 indices below 2^31 entries) and, when at hand,
        its transpose A^T (M, N)."""
        self.A, self._AT = A, AT
        self.shape = (int(A.shape[0]), int(A.shape[1]))

    @property
    def AT(self) -> torch.Tensor:
        """A^T (M, N) as CSR, transposed from A on first use (:func:`transpose_csr`) and kept."""
        if self._AT is None:
            ccol, row_t, val_t = transpose_csr(self.A.crow_indices(), self.A.col_indices(), self.A.values(),
                                               self.shape[1])
            self._AT = _csr(ccol, row_t, val_t, (self.shape[1], self.shape[0]))
        return self._AT

    @property
    def stores_transpose(self) -> bool:
        """Whether the adjoint needs A^T stored beside A (not on the CPU with the compiled kernels)."""
        return not compiled.available(self.device)

    @classmethod
    def from_coo(cls, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape) -> CsrOperator:
        """Build from COO triplets in any order (duplicates are summed)."""
        N, M = int(shape[0]), int(shape[1])
        coo = torch.sparse_coo_tensor(torch.stack([rows.long(), cols.long()]), values, (N, M)).coalesce()
        r, c = coo.indices()
        return cls.from_sorted_coo(r, c, coo.values(), (N, M))

    @classmethod
    def from_sorted_coo(cls, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape) -> CsrOperator:
        """Build from COO triplets sorted by row, then column, without duplicates."""
        N, M = int(shape[0]), int(shape[1])
        crow = torch.zeros(N + 1, dtype=torch.long, device=values.device)
        crow[1:] = torch.cumsum(torch.bincount(rows, minlength=N), 0)
        return cls.from_csr(crow, cols, values, (N, M))

    @classmethod
    def from_csr(cls, crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape) -> CsrOperator:
        """Build from the CSR arrays of A (N, M): row pointers (N + 1,), column indices and
        values (nnz,), columns ascending within each row; A^T, where the adjoint needs it
        (:attr:`stores_transpose`), by :func:`transpose_csr`."""
        N, M = int(shape[0]), int(shape[1])
        op = cls(_csr(crow, col, val, (N, M)))
        if op.stores_transpose:
            op.AT  # noqa: B018 - built now, where the assembly's memory is counted
        return op

    def rows(self, index: torch.Tensor) -> CsrOperator:
        """The operator of the rows ``index`` (R,) ascending: (R, M), A and A^T sliced from the
        stored ones (the same sums in the same order, without the rows left out), so a product
        reads only the rows kept."""
        index = index.to(self.device, torch.long)
        crow = self.A.crow_indices().long()
        starts, counts = crow[index], crow[index + 1] - crow[index]
        row = torch.repeat_interleave(torch.arange(index.numel(), device=self.device), counts)
        offset = torch.cumsum(counts, 0) - counts
        entry = starts.index_select(0, row) + torch.arange(row.numel(), device=self.device) - offset.index_select(0, row)
        crow_r = torch.zeros(index.numel() + 1, dtype=torch.long, device=self.device)
        torch.cumsum(counts, 0, out=crow_r[1:])
        return CsrOperator.from_csr(crow_r, self.A.col_indices()[entry], self.A.values()[entry],
                                    (index.numel(), self.shape[1]))

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
            return _CsrMatmul.apply(x, self)
        return csr_matmul(self.A, x)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        if self._compiled(y):
            return compiled.adjoint(self.A, y)
        return csr_matmul(self.AT, y)

    def residual_gradient(self, x: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """r = A x - b (N, C) and A^T r (M, C): on the CPU with the compiled kernels in one
        pass over A (the two products read it twice)."""
        if self._compiled(x):
            return compiled.residual_gradient(self.A, x, b)
        r = self.forward(x) - b
        return r, self.adjoint(r)

    def _compiled(self, v: torch.Tensor) -> bool:
        """Whether a product with ``v`` runs on the compiled kernels (CPU, A's dtype, no autograd)."""
        return compiled.available(v.device) and self.A.values().dtype == v.dtype and not (
            v.requires_grad and torch.is_grad_enabled())

    def to(self, device) -> CsrOperator:
        """The operator on ``device`` (A^T, where it is needed there, transposed on first use)."""
        return CsrOperator(self.A.to(device), None if self._AT is None else self._AT.to(device))

    def to_scipy(self):
        """A as ``scipy.sparse.csr_matrix`` (float32), for peers and dumps."""
        import scipy.sparse as sp

        A = self.A.cpu()
        return sp.csr_matrix(
            (A.values().numpy(), A.col_indices().numpy(), A.crow_indices().numpy()), shape=self.shape
        )
