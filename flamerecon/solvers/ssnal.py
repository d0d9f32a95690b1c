"""SSNAL: semismooth Newton augmented Lagrangian for the nonnegative LASSO (Li, Sun and Toh
2018, "A highly efficient semismooth Newton augmented Lagrangian method for solving Lasso
problems", SIAM J. Optim. 28(1)).

A is (N, M), b (N, C), the primal x (M, C) and the dual y (N, C). The dual of
min 0.5||A x - b||^2 + l1 sum(x), x >= 0, is min_y 0.5||y||^2 + <b, y> subject to
A^T y + l1 >= 0, and x is its multiplier. Each outer iteration minimises the augmented
Lagrangian in y,

    psi(y) = 0.5||y||^2 + <b, y> + ||max(x - sigma (A^T y + l1), 0)||^2 / (2 sigma),

strongly convex with gradient y + b - A x~(y), x~(y) = max(x - sigma (A^T y + l1), 0) (the
prox of sigma (l1 sum + the indicator of x >= 0)), by semismooth Newton: the system
(I + sigma A_J A_J^T) d = -grad on the voxels J where x~ > 0 is solved by conjugate gradients
in the ray space (Jacobi-preconditioned), the step found by Armijo backtracking on psi (free:
A^T d is computed once), until the paper's criterion (B) holds; then x <- x~(y) and sigma
grows. The duality gap is that of x with its residual (base.duality_gap), as for every solver.
The C colour columns are solved together (one product with C columns costs about one with one
on the CPU): each has its own J, CG coefficients and step.
"""

from __future__ import annotations

import torch

from flamerecon import interrupt
from flamerecon.operators.sparse import CsrOperator, csr_matmul
from flamerecon.solvers.base import Problem, Solver, gap_report, power_norm_sq, register


@register("ssnal")
class Ssnal(Solver):
    """Augmented Lagrangian on the dual, its subproblems by semismooth Newton-CG.

    One outer iteration costs, per Newton step, one A x, one A^T y and up to ``cg_iters``
    A x + A^T y pairs, plus one A x and two A^T y (the slack A^T y + l1 afresh, the duality
    gap). Stops when the relative duality gap
    (checked every ``check_every`` outer iterations) is below ``tol``, after ``max_iters``
    outer iterations, or at the first check past ``max_seconds`` (a Newton loop also ends
    there). ``sigma`` is the first penalty in units of 1/||A||^2, multiplied by
    ``sigma_growth`` after each outer iteration up to ``sigma_max``.
    """

    def __init__(self, max_iters: int = 100, tol: float = 1e-4, check_every: int = 1,
                 max_seconds: float | None = None, sigma: float = 1.0, sigma_growth: float = 5.0,
                 sigma_max: float = 1e4, newton_iters: int = 20, cg_iters: int = 200,
                 cg_tol: float = 0.1) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        for key, v in (("sigma", sigma), ("sigma_max", sigma_max)):
            if not float(v) > 0:
                raise ValueError(f"solver.{key} must be > 0, got {v}")
        if not 0 < float(cg_tol) < 1:
            raise ValueError(f"solver.cg_tol must be in (0, 1), got {cg_tol}")
        if not float(sigma_growth) >= 1:
            raise ValueError(f"solver.sigma_growth must be >= 1, got {sigma_growth}")
        for key, v in (("newton_iters", newton_iters), ("cg_iters", cg_iters)):
            if int(v) < 1:
                raise ValueError(f"solver.{key} must be >= 1, got {v}")
        self.sigma0, self.sigma_growth, self.sigma_max = float(sigma), float(sigma_growth), float(sigma_max)
        self.newton_iters, self.cg_iters, self.cg_tol = int(newton_iters), int(cg_iters), float(cg_tol)

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        A, b = problem.A, problem.b
        self.problem, self.x = problem, x
        L = power_norm_sq(A, A.shape[1], b.device, b.dtype)
        self.sigma = self.sigma0 / max(L, 1e-30)
        self.sigma_cap = self.sigma_max / max(L, 1e-30)
        self.r = A.forward(x) - b
        self.ATr = A.adjoint(self.r)
        self.y = self.r.clone()  # the dual point of x
        self.sq = _squared(A)
        self.info = self._measures()
        self.newton_steps = self.cg_steps = 0
        self.floor = (4 * torch.finfo(b.dtype).eps) ** 2 * float((b.double() ** 2).sum())
        return 1

    def step(self, it: int) -> None:
        A, b = self.problem.A, self.problem.b
        x, y, sigma = self.x, self.y, self.sigma
        w = A.adjoint(y) + self.problem.l1  # afresh: increments t A^T d accumulate rounding
        # the subproblem's accuracy: criterion (B) of the paper, ||grad||^2 <= delta^2 / sigma
        # ||x~ - x||^2 with a summable delta, above the rounding floor of y + b - A x~
        delta = 0.5 / it**1.1
        for k in range(self.newton_iters + 1):
            interrupt.check()
            v = x - sigma * w
            xt = v.clamp_min(0)
            Axt = A.forward(xt)
            grad = y + b - Axt
            gg = (grad.double() ** 2).sum(0)
            enough = max(delta**2 / sigma * float(((xt - x).double() ** 2).sum()), self.floor)
            if k == self.newton_iters or float(gg.sum()) <= enough:
                break
            if self.out_of_time():  # the subproblem unsolved: x (and its gap) stay as they were
                self.y = y
                return
            active = v > 0
            d = self._newton_direction(grad, active, sigma)
            ATd = A.adjoint(d)
            alpha = self._line_search(y, b, d, grad, v, ATd, sigma)
            if not bool((alpha > 0).any()):  # no decrease left in this precision
                break
            y = y + alpha * d
            w = w + alpha * ATd
            self.newton_steps += 1
        self.y = y
        self.x, self.r = xt, Axt - b
        self.ATr = A.adjoint(self.r)
        self.info = self._measures()
        self.sigma = min(self.sigma * self.sigma_growth, self.sigma_cap)

    def _newton_direction(self, grad: torch.Tensor, active: torch.Tensor,
                          sigma: float) -> torch.Tensor:
        """d (N, C) with (I + sigma A_J A_J^T) d ~= -grad per column (J: ``active``, (M, C)),
        by CG preconditioned with its diagonal 1 + sigma sum_{j in J} A_ij^2, until the
        residual falls by ``cg_tol``."""
        A = self.problem.A
        mask = active.to(grad.dtype)
        diag = 1.0 + sigma * csr_matmul(self.sq, mask) if self.sq is not None else torch.ones_like(grad)
        s = -grad
        z = s / diag
        p = z.clone()
        rz = (s.double() * z).sum(0)
        stop = self.cg_tol**2 * (s.double() ** 2).sum(0)
        d = torch.zeros_like(grad)
        for _ in range(self.cg_iters):
            interrupt.check()
            q = p + sigma * A.forward(A.adjoint(p) * mask)
            pq = (p.double() * q).sum(0)
            alpha = torch.where(pq > 0, rz / pq.clamp_min(1e-300), 0.0).to(d.dtype)
            d += alpha * p
            s -= alpha * q
            self.cg_steps += 1
            if bool(((s.double() ** 2).sum(0) <= stop).all()):
                break
            z = s / diag
            rz_new = (s.double() * z).sum(0)
            p = z + (rz_new / rz.clamp_min(1e-300)).to(d.dtype) * p
            rz = rz_new
        return d

    @staticmethod
    def _line_search(y, b, d, grad, v, ATd, sigma: float, trials: int = 30) -> torch.Tensor:
        """Per column the first t in 1, 1/2, ... with psi(y + t d) - psi(y) <= 1e-4 t <grad, d>
        (C,; 0 where none is found), the change of psi computed termwise in float64
        (v = x - sigma (A^T y + l1))."""
        y64, d64, v64, ATd64 = y.double(), d.double(), v.double(), ATd.double()
        bd, dd = ((y64 + b.double()) * d64).sum(0), (d64 * d64).sum(0)
        gd = (grad.double() * d64).sum(0)
        base = (v64.clamp_min(0) ** 2).sum(0)
        t = torch.ones(y.shape[1], dtype=torch.float64, device=y.device)
        done = torch.zeros(y.shape[1], dtype=torch.bool, device=y.device)
        for _ in range(trials):
            change = t * bd + 0.5 * t * t * dd + (((v64 - t * sigma * ATd64).clamp_min(0) ** 2).sum(0) - base) / (2 * sigma)
            done |= change <= 1e-4 * t * gd
            if bool(done.all()):
                break
            t = torch.where(done, t, 0.5 * t)
        return torch.where(done, t, 0.0).to(y.dtype)

    def _measures(self) -> dict[str, float]:
        return gap_report(self.problem, self.x, self.r, self.ATr)

    def report(self, it: int) -> dict[str, float]:
        return {**self.info, "sigma": self.sigma, "newton_steps": self.newton_steps,
                "cg_steps": self.cg_steps, "active_fraction": float((self.x > 0).double().mean())}

    def result(self, problem: Problem) -> tuple[torch.Tensor, float]:
        return self.x, self.info["objective"]


def _squared(A) -> torch.Tensor | None:
    """A (N, M) with its entries squared, whose product with the active mask is the diagonal
    of A_J A_J^T; None for an operator without a stored CSR (then CG is not preconditioned)."""
    if not isinstance(A, CsrOperator):
        return None
    M = A.A
    return torch.sparse_csr_tensor(M.crow_indices(), M.col_indices(), M.values() ** 2, size=M.shape)
