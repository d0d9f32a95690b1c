"""FISTA with adaptive restart for the nonnegative LASSO (Beck & Teboulle 2009;
O'Donoghue & Candes 2015 for the gradient restart)."""

from __future__ import annotations

import torch

from .base import Callback, Problem, Solver, SolveResult, duality_gap, power_norm_sq, register


@register("fista")
class Fista(Solver):
    """Accelerated proximal gradient; step 1/L with L = ||A||^2 from power iteration.

    Stops when the relative duality gap (checked every ``check_every`` iterations) is below
    ``tol``, after ``max_iters``, or at the first check past ``max_seconds`` (if set).
    """

    def __init__(self, max_iters: int = 500, tol: float = 1e-4, check_every: int = 10,
                 restart: bool = True, max_seconds: float | None = None, **_: object) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.restart = bool(restart)

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        return self.iterate(problem, x, callback)

    def iterate(self, problem: Problem, x: torch.Tensor, callback: Callback | None,
                lipschitz: float | None = None) -> SolveResult:
        """FISTA from ``x`` (M, C); ``lipschitz`` >= ||A||^2 if known (else power iteration)."""
        A, b, lam = problem.A, problem.b, problem.l1
        resume = self._take_resume()
        if resume is None:
            L = lipschitz if lipschitz is not None else 1.01 * power_norm_sq(
                A, A.shape[1], b.device, b.dtype)
            y, t, start, history = x.clone(), 1.0, 1, []
        else:  # continue exactly where state() was taken (x is resume["x"])
            L, t, start = resume["L"], resume["t"], resume["iteration"] + 1
            y, history = resume["y"].to(x), list(resume["history"])
        step = 1.0 / max(L, 1e-30)
        # the momentum t lives on the device, so an iteration never waits for the GPU
        t = torch.tensor(float(t), dtype=torch.float64, device=x.device)
        converged, it = False, start - 1
        for it in range(start, self.max_iters + 1):
            grad_y = A.adjoint(A.forward(y) - b)
            x_new = (y - step * (grad_y + lam)).clamp_min_(0)
            if self.restart:  # momentum points uphill: restart
                t = torch.where(((y - x_new) * (x_new - x)).sum() > 0, 1.0, t)
            t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt())
            y = x_new + ((t - 1.0) / t_new).to(x.dtype) * (x_new - x)
            x, t = x_new, t_new
            if it % self.check_every == 0 or it == self.max_iters:
                r = A.forward(x) - b
                primal, gap = duality_gap(problem, x, r, A.adjoint(r))
                info = {
                    "objective": primal,
                    "data": 0.5 * float((r.double() ** 2).sum()),
                    "l1": lam * float(x.double().sum()),
                    "gap": gap,
                    "rel_gap": gap / max(primal, 1e-30),
                }
                entry = {"iteration": it, **info}
                history.append(entry)
                if callback is not None:
                    self._state = {"iteration": it, "x": x, "y": y, "t": float(t), "L": L,
                                   "history": history}
                    callback(it, x, info)
                    entry.update(info)  # a callback may add entries (fista_smooth splits the data)
                if info["rel_gap"] < self.tol:
                    converged = True
                    break
                if self.out_of_time():
                    break
        return SolveResult(x, it, 0.0, problem.objective(x), converged, history)
