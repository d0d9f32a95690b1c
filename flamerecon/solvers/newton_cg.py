"""Projected Newton-CG for the nonnegative LASSO (Bertsekas 1982; Moré and Toraldo 1991).

The problem is a bound-constrained quadratic, F(x) = 0.5||Ax - b||^2 + l1 sum(x), x >= 0,
with Hessian A^T A. After a short FISTA warm start each outer step takes the free set
(x > 0, or x = 0 with a descending gradient), solves the Newton system A_F^T A_F d = -g_F by
conjugate gradients preconditioned with diag(A^T A), and accepts max(x + t d, 0) for the first
t in 1, 1/2, 1/4, ... that decreases F enough (Armijo), per colour column.
"""

from __future__ import annotations

import torch

from flamerecon import interrupt
from flamerecon.operators.sparse import CsrOperator
from flamerecon.solvers.base import (
    Callback,
    Problem,
    Solver,
    SolveResult,
    gap_report,
    power_norm_sq,
    register,
)
from flamerecon.solvers.fista import Fista


def column_norms_sq(A, M: int, dtype, device) -> torch.Tensor:
    """diag(A^T A) (M, 1): squared column norms of an assembled operator's A; ones (no
    preconditioning) for an operator without one."""
    if isinstance(A, CsrOperator):
        values = A.A.values()
        sq = torch.zeros(M, dtype=values.dtype, device=device).index_add_(0, A.A.col_indices().long(), values ** 2)
        return sq[:, None].to(dtype)
    return torch.ones(M, 1, dtype=dtype, device=device)


@register("newton_cg")
class NewtonCG(Solver):
    """Projected Newton with preconditioned CG on the free set, warm-started by FISTA.

    One outer iteration costs one A^T y, ``cg_iters`` (at most) A x + A^T y pairs and one A x
    per line-search trial. Stops when the relative duality gap (checked every
    ``check_every`` outer iterations) is below ``tol``, after ``max_iters`` outer iterations,
    or at the first check past ``max_seconds``.
    """

    def __init__(self, max_iters: int = 100, tol: float = 1e-4, check_every: int = 1,
                 max_seconds: float | None = None, warm_iters: int = 50, cg_iters: int = 40,
                 cg_tol: float = 1e-2) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.warm_iters = int(warm_iters)
        self.cg_iters = int(cg_iters)
        self.cg_tol = float(cg_tol)

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        A, b, lam = problem.A, problem.b, problem.l1
        L = 1.01 * power_norm_sq(A, A.shape[1], b.device, b.dtype)
        history: list[dict] = []
        if self.warm_iters > 0:
            warm = Fista(max_iters=self.warm_iters, tol=self.tol, check_every=self.warm_iters)
            warm._started = self._started
            x = warm.iterate(problem, x, None, lipschitz=L).x
        diag = column_norms_sq(A, A.shape[1], b.dtype, b.device).clamp_min(1e-30)
        r = A.forward(x) - b
        ATr = A.adjoint(r)
        f = 0.5 * (r.double() ** 2).sum(0) + lam * x.double().sum(0)
        converged, it = False, 0
        for it in range(1, self.max_iters + 1):
            interrupt.check()
            g = ATr + lam
            free = (x > 0) | (g < 0)
            d = self._newton_direction(A, g, free, diag)
            x, r, f, t = self._line_search(A, b, lam, x, r, f, g, d, L)
            ATr = A.adjoint(r)
            if it % self.check_every == 0 or it == self.max_iters:
                info = {**gap_report(problem, x, r, ATr), "free_fraction": float(free.double().mean()), "step": t}
                history.append({"iteration": it, **info})
                if callback is not None:
                    callback(it, x, info)
                if info["rel_gap"] < self.tol:
                    converged = True
                    break
                if self.out_of_time():
                    break
        return SolveResult(x, it, 0.0, problem.objective(x), converged, history)

    def _newton_direction(self, A, g: torch.Tensor, free: torch.Tensor,
                          diag: torch.Tensor) -> torch.Tensor:
        """d (M, C) on the free set with A_F^T A_F d ~= -g_F (Jacobi-preconditioned CG, per
        column, until the preconditioned residual falls by ``cg_tol`` or ``cg_iters``)."""
        mask = free.to(g.dtype)
        s = -g * mask
        z = s / diag
        p = z.clone()
        rz = (s * z).sum(0)
        stop = self.cg_tol**2 * rz
        d = torch.zeros_like(g)
        for _ in range(self.cg_iters):
            interrupt.check()
            q = A.adjoint(A.forward(p)) * mask
            pq = (p * q).sum(0)
            alpha = torch.where((pq > 0) & (rz > stop), rz / pq.clamp_min(1e-300), 0.0)
            d += alpha * p
            s -= alpha * q
            z = s / diag
            rz_new = (s * z).sum(0)
            if bool((rz_new <= stop).all()):
                break
            p = z + (rz_new / rz.clamp_min(1e-300)) * p
            rz = rz_new
        return d

    @staticmethod
    def _line_search(A, b, lam: float, x, r, f, g, d, L: float, trials: int = 8):
        """Projected backtracking along d, per column; a column where no trial decreases F
        takes a projected gradient step 1/L (which always does). Returns x, A x - b, F (C,) and
        the accepted t per column (0: the gradient step)."""
        x_new, r_new, f_new = x.clone(), r.clone(), f.clone()
        done = torch.zeros(x.shape[1], dtype=torch.bool, device=x.device)
        t, accepted = 1.0, torch.zeros(x.shape[1], dtype=torch.float64)
        for _ in range(trials):
            xt = (x + t * d).clamp_min_(0)
            rt = A.forward(xt) - b
            ft = 0.5 * (rt.double() ** 2).sum(0) + lam * xt.double().sum(0)
            ok = ~done & (ft <= f + 1e-4 * (g.double() * (xt - x).double()).sum(0))
            x_new[:, ok], r_new[:, ok], f_new[ok] = xt[:, ok], rt[:, ok], ft[ok]
            done |= ok
            accepted[ok.cpu()] = t
            if bool(done.all()):
                return x_new, r_new, f_new, accepted.tolist()
            t *= 0.5
        xt = (x - g / L).clamp_min_(0)
        rt = A.forward(xt) - b
        ft = 0.5 * (rt.double() ** 2).sum(0) + lam * xt.double().sum(0)
        x_new[:, ~done], r_new[:, ~done], f_new[~done] = xt[:, ~done], rt[:, ~done], ft[~done]
        return x_new, r_new, f_new, accepted.tolist()
