"""CGLS: conjugate gradients on the normal equations, the least-squares ("LSM") baseline.

Minimises 0.5||A x - b||^2 + 0.5 damp^2 ||x||^2 per channel (the L1 weight of the problem is
ignored: this is the unregularised reference the paper argues against). Densities may come out
negative; ``nonneg`` clamps the final result for rendering.
"""

from __future__ import annotations

import torch

from flamerecon.solvers.base import Problem, Solver, register


@register("cgls")
class Cgls(Solver):
    """CGLS (Hestenes-Stiefel on A^T A), all channels at once with per-channel step sizes.

    Stops when ||A^T r - damp^2 x|| <= tol * ||A^T b|| in every channel, after ``max_iters``,
    or at the first check past ``max_seconds``.
    """

    def __init__(self, max_iters: int = 200, tol: float = 1e-6, damp: float = 0.0,
                 nonneg: bool = False, check_every: int = 10,
                 max_seconds: float | None = None) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.damp2 = float(damp) ** 2
        self.nonneg = bool(nonneg)

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        A, b = problem.A, problem.b
        self.problem, self.x = problem, x
        self.r = b - A.forward(x)
        s = A.adjoint(self.r) - self.damp2 * x  # negative gradient of the damped LS objective
        self.p = s.clone()
        self.gamma = (s.double() ** 2).sum(0)
        self.stop = self.tol * A.adjoint(b).double().norm(dim=0)
        self.converged = bool((self.gamma.sqrt() <= self.stop).all())
        return 1

    def step(self, it: int) -> None:
        A, x, p, gamma = self.problem.A, self.x, self.p, self.gamma
        q = A.forward(p)
        denom = (q.double() ** 2).sum(0) + self.damp2 * (p.double() ** 2).sum(0)
        alpha = torch.where(denom > 0, gamma / denom.clamp_min(1e-300), torch.zeros_like(gamma))
        self.x = x = x + alpha.to(x.dtype) * p
        self.r = self.r - alpha.to(x.dtype) * q
        s = A.adjoint(self.r) - self.damp2 * x
        gamma_new = (s.double() ** 2).sum(0)
        beta = torch.where(gamma > 0, gamma_new / gamma.clamp_min(1e-300), torch.zeros_like(gamma))
        self.p = s + beta.to(x.dtype) * p
        self.gamma = gamma_new
        self.converged = bool((gamma_new.sqrt() <= self.stop).all())

    def is_check(self, it: int) -> bool:
        return self.converged or super().is_check(it)

    def report(self, it: int) -> dict[str, float]:
        data = 0.5 * float((self.r.double() ** 2).sum())
        l1 = self.problem.l1 * float(self.x.double().abs().sum())
        return {"objective": data + l1, "data": data, "l1": l1,
                "grad_norm": float(self.gamma.sum().sqrt())}

    def reached(self, info: dict) -> bool:
        return self.converged

    def reached_at_start(self) -> bool:
        return self.converged

    def result(self, problem: Problem) -> tuple[torch.Tensor, float]:
        x = self.x.clamp_min(0) if self.nonneg else self.x
        return x, problem.objective(x)
