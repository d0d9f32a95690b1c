"""MART, the multiplicative algebraic reconstruction technique (Gordon, Bender & Herman 1970),
the first reconstruction of tomographic PIV (Elsinga et al. 2006) and chemiluminescence
tomography. A row-action method: for each row i (pixel p_i, ray weights a_i) in turn,

    x_j <- x_j * (p_i / (a_i . x)) ** (relax * a_ij / max_k a_ik)       for every voxel j

from a positive start; one sweep over every row is one iteration. On a consistent nonnegative
system it converges to the nonnegative solution nearest the start in Kullback-Leibler distance
(from a uniform start: the maximum-entropy one; Lent 1977). A pixel of 0 zeroes every voxel on
its ray (MART carves); it fits the data only (the L1 weight of the problem is ignored).

The rows are visited in blocks whose rays share no voxel (a greedy colouring of the rows,
computed once per operator: a few hundred blocks on the default problems): within a block the
updates touch disjoint voxels, so applying them together is exactly applying them one after the
other; a sweep is the textbook row-action MART with the rows in that order, block by block
(``order: shuffled``: the blocks in a new random order each sweep). It needs A's rows: the
assembled operator (``projector.backend=assembled``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from flamerecon.errors import ConfigError
from flamerecon.operators.sparse import CsrOperator
from flamerecon.solvers.base import Problem, Solver, density_scale, register

#: MART's start where none is given: this many times the best constant density (Tomo-PIV's
#: uniform first guess, at the level of the data)
START = 1.0
ORDERS = ("fixed", "shuffled")
#: the most blocks of rows a sweep visits (each a few small products): a few hundred on the
#: default problems (746 on the synthetic flame, 423 on ScalarFlow at 1/4 on 128 cells)
MAX_BLOCKS = 4096


def row_blocks(A: CsrOperator) -> list[torch.Tensor]:
    """Rows of ``A`` (those with an entry) in blocks whose rows share no column, each a (R,)
    long tensor: a greedy first-fit colouring in row order (each row takes the first block none
    of whose rows touches its voxels; a bit set of the blocks per voxel). At most
    :data:`MAX_BLOCKS`: rays that share voxels more densely (a grid far coarser than the pixels)
    are a ConfigError, not a sweep of one ray at a time. Cached on ``A``."""
    cached = getattr(A, "_mart_blocks", None)
    if cached is not None:
        return cached
    crow, col = A.A.crow_indices().cpu().numpy(), A.A.col_indices().cpu().numpy()
    N, M = A.shape
    used = np.zeros((M, MAX_BLOCKS // 64), np.uint64)  # bit b of word w: block 64 w + b touches the voxel
    block = np.full(N, -1, np.int64)
    for i in range(N):
        cols = col[crow[i]:crow[i + 1]]
        if cols.size == 0:
            continue
        free = ~np.bitwise_or.reduce(used[cols], axis=0)
        words = np.flatnonzero(free)
        if words.size == 0:
            raise ConfigError(f"solver=mart: the rays share voxels too densely for its blocks ({N} rays on {M} "
                              f"voxels; ray {i} meets all of the first {MAX_BLOCKS} blocks); use a finer grid "
                              "(grid.resolution) or coarser images (scene.downscale)")
        w = int(words[0])
        bit = (int(free[w]) & -int(free[w])).bit_length() - 1
        block[i] = 64 * w + bit
        used[cols, w] |= np.uint64(1 << bit)
    order = np.argsort(block, kind="stable")
    counts = np.bincount(block[block >= 0])
    starts = np.searchsorted(block[order], np.arange(len(counts)))
    rows = torch.from_numpy(order).to(A.device)
    blocks = [rows[s:s + n] for s, n in zip(starts.tolist(), counts.tolist())]
    A._mart_blocks = blocks
    return blocks


class _Block:
    """One block's entries as flat arrays (its rows share no voxel): ``rows`` (R,) in A,
    ``where`` (nnz,) each entry's row within the block, ``cols`` (nnz,) voxels (distinct),
    ``values`` (nnz,), and ``peak`` (R, 1) the largest entry of each row."""

    def __init__(self, A: CsrOperator, rows: torch.Tensor) -> None:
        crow, col, val = A.A.crow_indices().long(), A.A.col_indices().long(), A.A.values()
        counts = crow[rows + 1] - crow[rows]
        self.rows = rows
        self.where = torch.repeat_interleave(torch.arange(len(rows), device=rows.device), counts)
        entry = crow[rows].index_select(0, self.where) + torch.arange(int(counts.sum()), device=rows.device) - (
            torch.cumsum(counts, 0) - counts).index_select(0, self.where)
        self.cols, self.values = col[entry], val[entry]
        self.peak = val.new_zeros(len(rows)).scatter_reduce_(0, self.where, self.values, "amax")[:, None]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """a_i . x for the block's rows: (R, C)."""
        return x.new_zeros(len(self.rows), x.shape[1]).index_add_(0, self.where, self.values[:, None] * x[self.cols])


@register("mart")
class Mart(Solver):
    """Row-action MART with relaxation ``relax`` in (0, 1] (Tomo-PIV's usual 1), the rows in
    conflict-free blocks visited in a ``fixed`` or ``shuffled`` order; the start is the best
    constant density (a warm start's zeros are lifted to a millionth of it: MART keeps a zero).

    Stops when the data residual ||A x - b|| changed by less than ``tol`` (relative) over the
    last ``check_every`` sweeps, after ``max_iters`` sweeps, or at the first check past
    ``max_seconds``. Negative pixels count as 0.
    """

    def __init__(self, max_iters: int = 20, tol: float = 1e-3, relax: float = 1.0, order: str = "fixed",
                 check_every: int = 1, max_seconds: float | None = None) -> None:
        if not 0.0 < float(relax) <= 1.0:
            raise ValueError(f"solver.relax: got {relax}; MART's relaxation must be > 0 and <= 1")
        if order not in ORDERS:
            raise ValueError(f"solver.order: unknown order {order!r}; solver.order must be fixed or shuffled")
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.relax, self.order = float(relax), order

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        A = problem.A
        if not isinstance(A, CsrOperator):
            raise ConfigError("solver=mart: its row-action updates read the operator's rows; set "
                              "projector.backend=assembled (it got a matrix-free operator)")
        self.problem, self.b = problem, problem.b.clamp_min(0.0)
        dtype, device = self.b.dtype, self.b.device
        level = density_scale(A, self.b)  # (C,)
        start = (x.amax(0) <= 0) if x.numel() else torch.ones(x.shape[1], dtype=torch.bool)
        seen = A.adjoint(torch.ones(A.shape[0], 1, dtype=dtype, device=device)) > 0  # (M, 1)
        x = torch.where(start, START * level, x.clamp_min(1e-6 * START * level))
        self.x = torch.where(seen, x, torch.zeros_like(x))  # no ray: no information, no density
        self.blocks = [_Block(A, rows) for rows in row_blocks(A)]
        self.generator = torch.Generator().manual_seed(0)  # the shuffled order: the same each solve
        self.last = math.inf
        return 1

    def step(self, it: int) -> None:
        order = (torch.randperm(len(self.blocks), generator=self.generator).tolist() if self.order == "shuffled"
                 else range(len(self.blocks)))
        for k in order:
            block = self.blocks[k]
            p, q = self.b[block.rows], block.forward(self.x)  # (R, C)
            zero = p <= 0  # p_i = 0: every voxel on its ray to 0 (0 ** w = 0 for w > 0)
            ratio = torch.where(zero | (q <= 0), torch.ones_like(p), p / q.clamp_min(1e-30))
            power = self.relax * torch.log(ratio) / block.peak.clamp_min(1e-30)  # (R, C)
            factor = torch.exp(block.values[:, None] * power[block.where])  # one row per voxel: (nnz, C)
            factor = torch.where(zero[block.where] & (block.values[:, None] > 0), torch.zeros_like(factor), factor)
            self.x[block.cols] *= factor

    def report(self, it: int) -> dict[str, float]:
        r = self.problem.A.forward(self.x) - self.problem.b
        data = 0.5 * float((r.double() ** 2).sum())
        l1 = self.problem.l1 * float(self.x.double().abs().sum())
        return {"objective": data + l1, "data": data, "l1": l1, "residual": math.sqrt(2 * data)}

    def reached(self, info: dict) -> bool:  # not at the first check: there is nothing to compare yet
        return math.isfinite(self.last) and abs(self.last - info["residual"]) <= self.tol * self.last

    def after_check(self, info: dict) -> None:
        self.last = info["residual"]
