"""SART, the algebraic reconstruction baseline (Andersen & Kak 1984), simultaneous form:

    x <- max(0, x + relax * V^-1 A^T W (b - A x)),   W = diag(1 / row sums), V = diag(col sums)

It fits the data only (the L1 weight of the problem is ignored). For 0 < relax < 2 each step
decreases the W-weighted residual ||A x - b||_W (a projected gradient step in the V metric,
whose Lipschitz constant is <= 1 for nonnegative A).
"""

from __future__ import annotations

import math

import torch

from flamerecon.solvers.base import Problem, Solver, register


@register("sart")
class Sart(Solver):
    """Simultaneous SART with the nonnegativity clamp and relaxation ``relax`` in (0, 2).

    Stops when the weighted residual decreased by less than ``tol`` (relative) over the last
    ``check_every`` iterations, after ``max_iters``, or at the first check past ``max_seconds``.
    Assumes a nonnegative operator.
    """

    def __init__(self, max_iters: int = 200, tol: float = 1e-5, relax: float = 1.0,
                 nonneg: bool = True, check_every: int = 10,
                 max_seconds: float | None = None) -> None:
        if not 0.0 < float(relax) < 2.0:
            raise ValueError(f"solver.relax must lie in (0, 2), got {relax}")
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.relax = float(relax)
        self.nonneg = bool(nonneg)

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        A, b = problem.A, problem.b
        dtype, device = b.dtype, b.device
        self.problem, self.x = problem, x
        row_sums = A.forward(torch.ones(A.shape[1], 1, dtype=dtype, device=device))
        col_sums = A.adjoint(torch.ones(A.shape[0], 1, dtype=dtype, device=device))
        self.w = torch.where(row_sums > 0, 1.0 / row_sums, torch.zeros_like(row_sums))
        self.v = torch.where(col_sums > 0, self.relax / col_sums, torch.zeros_like(col_sums))
        self.last = float("inf")
        self.r = b - A.forward(x)
        return 1

    def step(self, it: int) -> None:
        A, b = self.problem.A, self.problem.b
        self.x = self.x + self.v * A.adjoint(self.w * self.r)
        if self.nonneg:
            self.x.clamp_min_(0)
        self.r = b - A.forward(self.x)

    def report(self, it: int) -> dict[str, float]:
        r = self.r
        weighted = 0.5 * float((self.w * r.double() ** 2).sum())
        data = 0.5 * float((r.double() ** 2).sum())
        l1 = self.problem.l1 * float(self.x.double().abs().sum())
        return {"objective": data + l1, "data": data, "l1": l1, "weighted_residual": weighted}

    def reached(self, info: dict) -> bool:  # not at the first check: there is nothing to compare yet
        return math.isfinite(self.last) and self.last - info["weighted_residual"] <= self.tol * self.last

    def after_check(self, info: dict) -> None:
        self.last = info["weighted_residual"]
