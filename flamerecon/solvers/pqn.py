"""Projected quasi-Newton (L-BFGS) for the nonnegative LASSO (Kim, Sra and Dhillon 2010).

On x >= 0 the objective is the smooth quadratic 0.5||A x - b||^2 + l1 sum(x). Per colour
column, each iteration holds the voxels at 0 whose gradient points outward, takes the L-BFGS
direction on the others (the two-loop recursion over the last ``memory`` pairs applied to the
masked gradient: the free block of the inverse-Hessian approximation) and backtracks along the
projection max(0, x + t d) from t = 1 until the objective decreases enough (Armijo, on the
change F(x_t) - F(x) = g.s + 0.5||A s||^2, s = x_t - x, which keeps its relative accuracy
where the values of F no longer differ in floating point). An iteration costs one A x and one A^T y when t = 1 is accepted (each further trial one A x);
the duality gap at a check costs nothing more, A x - b and A^T (A x - b) being at hand.
"""

from __future__ import annotations

import torch

from flamerecon.operators import residual_gradient
from flamerecon.solvers.base import Problem, Solver, gap_report, register


@register("pqn")
class ProjectedQuasiNewton(Solver):
    """Projected L-BFGS with ``memory`` pairs per column. Stops when the relative duality gap
    (checked every ``check_every`` iterations) is below ``tol``, after ``max_iters``, or at
    the first check past ``max_seconds`` (if set). Resumes exactly from its :meth:`state`.
    """

    trials = 20  # Armijo halvings before a column drops its pairs and starts over

    def __init__(self, max_iters: int = 500, tol: float = 1e-4, check_every: int = 10,
                 memory: int = 10, max_seconds: float | None = None) -> None:
        super().__init__(max_iters, tol, check_every, max_seconds)
        if int(memory) < 1:
            raise ValueError(f"solver.memory must be >= 1, got {memory}")
        self.memory = int(memory)

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        self.problem, self.x = problem, x
        if resume is None:
            self.r = problem.A.forward(x) - problem.b
            self.g = problem.A.adjoint(self.r) + problem.l1
            self.pairs: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
            self.gamma: torch.Tensor | None = None
            start = 1
        else:  # continue exactly where state() was taken (x is resume["x"])
            self.r, self.g = resume["r"].to(x), resume["g"].to(x)
            self.pairs = [tuple(t.to(x.device) for t in pair) for pair in resume["pairs"]]
            self.gamma = None if resume["gamma"] is None else resume["gamma"].to(x.device)
            start = resume["iteration"] + 1
        return start

    def direction(self, g: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        """-H g on the free voxels (M, C), 0 on the held ones: the two-loop recursion on the
        masked gradient, scaled by ``gamma`` (C,), s.y / y.y of the newest pair."""
        q = g * free
        alphas = []
        for s, y, rho in reversed(self.pairs):
            alpha = rho * (s * q).sum(0)
            alphas.append(alpha)
            q -= alpha * y
        q *= self.gamma
        for (s, y, rho), alpha in zip(self.pairs, reversed(alphas)):
            q += (alpha - rho * (y * q).sum(0)) * s
        return -q * free

    def step(self, it: int) -> None:
        A, lam = self.problem.A, self.problem.l1
        x, g = self.x, self.g
        free = ~((x <= 0) & (g > 0))
        if self.gamma is None:  # no curvature yet: the exact minimiser along -g (free part)
            Ag = A.forward(g * free)
            self.gamma = ((g * g * free).sum(0) / (Ag * Ag).sum(0).clamp_min(1e-30)).nan_to_num(0.0)
        d = self.direction(g, free)
        x_new, r_new, grad, failed = self.line_search(x, g, d)
        g_new = (A.adjoint(r_new) if grad is None else grad) + lam
        s, y = x_new - x, g_new - g
        sy, yy = (s * y).sum(0), (y * y).sum(0)
        curved = sy > 0
        rho = torch.where(curved, 1.0 / sy.where(curved, 1.0), 0.0)  # 0: the pair does nothing
        self.pairs = [*self.pairs[1 - self.memory:], (s, y, rho)] if self.memory > 1 else [(s, y, rho)]
        self.gamma = torch.where(curved, sy / yy.where(curved, 1.0), self.gamma)
        if failed:  # a column found no decrease along its direction: forget the curvature
            self.pairs, self.gamma = [], None
        self.x, self.r, self.g = x_new, r_new, g_new

    def line_search(self, x: torch.Tensor, g: torch.Tensor, d: torch.Tensor):
        """Per column the first t in 1, 1/2, 1/4, ... with F(x_t) - F(x) <= 1e-4 g.s for
        x_t = max(0, x + t d), s = x_t - x; returns x and A x - b there, A^T (A x - b) when
        every column took t = 1 (its first trial makes both in one pass over A: the usual
        step costs one pass, not two; None otherwise), and whether a column found none (it
        keeps its x)."""
        A, b = self.problem.A, self.problem.b
        x_new, r_new = x.clone(), self.r.clone()
        done = torch.zeros(x.shape[1], dtype=torch.bool, device=x.device)
        t = torch.ones(x.shape[1], dtype=x.dtype, device=x.device)
        for trial in range(self.trials):
            xt = (x + t * d).clamp_min_(0)
            if trial == 0:
                rt, grad = residual_gradient(A, xt, b)
            else:
                rt, grad = A.forward(xt) - b, None
            gs = (g * (xt - x)).double().sum(0)
            As = (rt - self.r).double()
            ok = ~done & (0.5 * (As * As).sum(0) <= -(1 - 1e-4) * gs)
            x_new = torch.where(ok, xt, x_new)
            r_new = torch.where(ok, rt, r_new)
            done |= ok
            if bool(done.all()):
                return x_new, r_new, grad if trial == 0 else None, False
            t = torch.where(done, t, 0.5 * t)
        return x_new, r_new, None, True

    def report(self, it: int) -> dict[str, float]:
        return gap_report(self.problem, self.x, self.r, self.g - self.problem.l1)

    def result(self, problem: Problem) -> tuple[torch.Tensor, float]:
        """x and the objective of the problem iterated on (stacked too), from its residual."""
        r, x = self.r.double(), self.x.double()
        return self.x, 0.5 * float((r * r).sum()) + self.problem.l1 * float(x.sum())

    def snapshot(self, it: int) -> dict:
        return {"iteration": it, "x": self.x, "r": self.r, "g": self.g, "pairs": list(self.pairs),
                "gamma": self.gamma, "history": self.history}
