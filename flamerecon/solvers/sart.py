"""SART, the algebraic reconstruction baseline (Andersen & Kak 1984), simultaneous form:

    x <- max(0, x + relax * V^-1 A^T W (b - A x)),   W = diag(1 / row sums), V = diag(col sums)

It fits the data only (the L1 weight of the problem is ignored). For 0 < relax < 2 each step
decreases the W-weighted residual ||A x - b||_W (a projected gradient step in the V metric,
whose Lipschitz constant is <= 1 for nonnegative A).
"""

from __future__ import annotations

import torch

from .base import Callback, Problem, Solver, SolveResult, register


@register("sart")
class Sart(Solver):
    """Simultaneous SART with the nonnegativity clamp and relaxation ``relax`` in (0, 2).

    Stops when the weighted residual decreased by less than ``tol`` (relative) over the last
    ``check_every`` iterations, after ``max_iters``, or at the first check past ``max_seconds``.
    Assumes a nonnegative operator.
    """

    def __init__(self, max_iters: int = 200, tol: float = 1e-5, relax: float = 1.0,
                 nonneg: bool = True, check_every: int = 10, max_seconds: float | None = None,
                 **_: object) -> None:
        if not 0.0 < float(relax) < 2.0:
            raise ValueError(f"solver.relax must lie in (0, 2), got {relax}")
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.relax = float(relax)
        self.nonneg = bool(nonneg)

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        A, b = problem.A, problem.b
        dtype, device = b.dtype, b.device
        row_sums = A.forward(torch.ones(A.shape[1], 1, dtype=dtype, device=device))
        col_sums = A.adjoint(torch.ones(A.shape[0], 1, dtype=dtype, device=device))
        w = torch.where(row_sums > 0, 1.0 / row_sums, torch.zeros_like(row_sums))
        v = torch.where(col_sums > 0, self.relax / col_sums, torch.zeros_like(col_sums))
        history: list[dict] = []
        last = float("inf")
        converged, it = False, 0
        r = b - A.forward(x)
        for it in range(1, self.max_iters + 1):
            x = x + v * A.adjoint(w * r)
            if self.nonneg:
                x.clamp_min_(0)
            r = b - A.forward(x)
            if it % self.check_every == 0 or it == self.max_iters:
                weighted = 0.5 * float((w * r.double() ** 2).sum())
                data = 0.5 * float((r.double() ** 2).sum())
                l1 = problem.l1 * float(x.double().abs().sum())
                info = {"objective": data + l1, "data": data, "l1": l1,
                        "weighted_residual": weighted}
                history.append({"iteration": it, **info})
                if callback is not None:
                    callback(it, x, info)
                if last - weighted <= self.tol * last:
                    converged = True
                    break
                if self.out_of_time():
                    break
                last = weighted
        return SolveResult(x, it, 0.0, problem.objective(x), converged, history)
