"""CGLS: conjugate gradients on the normal equations, the least-squares ("LSM") baseline.

Minimises 0.5||A x - b||^2 + 0.5 damp^2 ||x||^2 per channel (the L1 weight of the problem is
ignored: this is the unregularised reference the paper argues against). Densities may come out
negative; ``nonneg`` clamps the final result for rendering.
"""

from __future__ import annotations

import torch

from .base import Callback, Problem, Solver, SolveResult, register


@register("cgls")
class Cgls(Solver):
    """CGLS (Hestenes-Stiefel on A^T A), all channels at once with per-channel step sizes.

    Stops when ||A^T r - damp^2 x|| <= tol * ||A^T b|| in every channel, after ``max_iters``,
    or at the first check past ``max_seconds``.
    """

    def __init__(self, max_iters: int = 200, tol: float = 1e-6, damp: float = 0.0,
                 nonneg: bool = False, check_every: int = 10, max_seconds: float | None = None,
                 **_: object) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.damp2 = float(damp) ** 2
        self.nonneg = bool(nonneg)

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        A, b = problem.A, problem.b
        r = b - A.forward(x)
        s = A.adjoint(r) - self.damp2 * x  # negative gradient of the damped LS objective
        p = s.clone()
        gamma = (s.double() ** 2).sum(0)
        stop = self.tol * A.adjoint(b).double().norm(dim=0)
        history: list[dict] = []
        converged, it = bool((gamma.sqrt() <= stop).all()), 0
        while not converged and it < self.max_iters:
            it += 1
            q = A.forward(p)
            denom = (q.double() ** 2).sum(0) + self.damp2 * (p.double() ** 2).sum(0)
            alpha = torch.where(denom > 0, gamma / denom.clamp_min(1e-300), torch.zeros_like(gamma))
            x = x + alpha.to(x.dtype) * p
            r = r - alpha.to(x.dtype) * q
            s = A.adjoint(r) - self.damp2 * x
            gamma_new = (s.double() ** 2).sum(0)
            beta = torch.where(gamma > 0, gamma_new / gamma.clamp_min(1e-300), torch.zeros_like(gamma))
            p = s + beta.to(x.dtype) * p
            gamma = gamma_new
            converged = bool((gamma.sqrt() <= stop).all())
            if it % self.check_every == 0 or converged or it == self.max_iters:
                data = 0.5 * float((r.double() ** 2).sum())
                l1 = problem.l1 * float(x.double().abs().sum())
                info = {"objective": data + l1, "data": data, "l1": l1,
                        "grad_norm": float(gamma.sum().sqrt())}
                history.append({"iteration": it, **info})
                if callback is not None:
                    callback(it, x, info)
                if self.out_of_time():
                    break
        if self.nonneg:
            x = x.clamp_min(0)
        return SolveResult(x, it, 0.0, problem.objective(x), converged, history)
