"""FISTA with adaptive restart for the nonnegative LASSO (Beck & Teboulle 2009;
O'Donoghue & Candes 2015 for the gradient restart)."""

from __future__ import annotations

import torch

from flamerecon.operators import residual_gradient
from flamerecon.solvers.base import (
    Callback,
    Problem,
    Solver,
    SolveResult,
    gap_report,
    power_norm_sq,
    register,
)


@register("fista")
class Fista(Solver):
    """Accelerated proximal gradient; step 1/L with L = ||A||^2 from power iteration.

    Stops when the relative duality gap (checked every ``check_every`` iterations) is below
    ``tol``, after ``max_iters``, or at the first check past ``max_seconds`` (if set).
    """

    def __init__(self, max_iters: int = 500, tol: float = 1e-4, check_every: int = 10,
                 restart: bool = True, max_seconds: float | None = None) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.restart = bool(restart)

    _lipschitz: float | None = None  # from iterate(), for its one run

    def iterate(self, problem: Problem, x: torch.Tensor, callback: Callback | None,
                lipschitz: float | None = None) -> SolveResult:
        """FISTA from ``x`` (M, C) as :meth:`solve` runs it but untimed (for a solver that starts
        with FISTA steps); ``lipschitz`` >= ||A||^2 if known (else power iteration)."""
        self._lipschitz = lipschitz
        try:
            return self._run(problem, x, callback)
        finally:
            self._lipschitz = None

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None,
               lipschitz: float | None = None) -> int:
        """FISTA from ``x`` (M, C); ``lipschitz`` >= ||A||^2 if known (else power iteration)."""
        A, b = problem.A, problem.b
        self.problem, self.x = problem, x
        lipschitz = self._lipschitz if lipschitz is None else lipschitz
        if resume is None:
            L = lipschitz if lipschitz is not None else 1.01 * power_norm_sq(
                A, A.shape[1], b.device, b.dtype)
            self.y, t, start = x.clone(), 1.0, 1
        else:  # continue exactly where state() was taken (x is resume["x"])
            L, t, start = resume["L"], resume["t"], resume["iteration"] + 1
            self.y = resume["y"].to(x)
        self.L, self.step_size = L, 1.0 / max(L, 1e-30)
        # the momentum t lives on the device, so an iteration never waits for the GPU
        self.t = torch.tensor(float(t), dtype=torch.float64, device=x.device)
        return start

    def step(self, it: int) -> None:
        A, b, lam = self.problem.A, self.problem.b, self.problem.l1
        x, y, t = self.x, self.y, self.t
        grad_y = residual_gradient(A, y, b)[1]  # one pass over an assembled A
        x_new = (y - self.step_size * (grad_y + lam)).clamp_min_(0)
        if self.restart:  # momentum points uphill: restart
            t = torch.where(((y - x_new) * (x_new - x)).sum() > 0, 1.0, t)
        t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt())
        self.y = x_new + ((t - 1.0) / t_new).to(x.dtype) * (x_new - x)
        self.x, self.t = x_new, t_new

    def report(self, it: int) -> dict[str, float]:
        problem, x = self.problem, self.x
        A, b = problem.A, problem.b
        r = A.forward(x) - b
        return gap_report(problem, x, r, A.adjoint(r))

    def snapshot(self, it: int) -> dict:
        return {"iteration": it, "x": self.x, "y": self.y, "t": float(self.t), "L": self.L,
                "history": self.history}

    def result(self, problem: Problem) -> tuple[torch.Tensor, float]:
        return self.x, self.problem.objective(self.x)  # of the problem iterated on (stacked too)
