"""Adam on the nonnegative LASSO by autograd through the operator's forward (the
differentiable-renderer route: works for any operator whose ``forward`` torch can differentiate,
e.g. the matrix-free projector or :class:`~flamerecon.operators.CsrOperator`)."""

from __future__ import annotations

import math

import torch

from flamerecon.solvers.base import Problem, Solver, density_scale, gap_report, register


@register("adam")
class Adam(Solver):
    """Adam on 0.5||Ax-b||^2 + l1*sum(x), densities clamped to >= 0 after every step.

    ``lr`` is relative to the problem's density scale (the best constant fit
    ``<A 1, b> / ||A 1||^2`` per channel), so one default suits any units. The step size
    follows a cosine from ``lr`` down to ``lr * lr_final`` over ``max_iters``, and is
    halved whenever the objective has not improved over ``patience`` checks (one check every
    ``check_every`` iterations).
    Stops when the relative duality gap (computed from the gradient autograd already gives)
    is below ``tol``, after ``max_iters``, or at the first check past ``max_seconds``.
    """

    def __init__(self, lr: float = 0.05, max_iters: int = 2000, tol: float = 1e-4,
                 check_every: int = 10, lr_final: float = 1e-3, patience: int = 3,
                 max_seconds: float | None = None) -> None:
        if lr <= 0 or lr_final <= 0:
            raise ValueError(f"solver.lr and solver.lr_final must be > 0 (got {lr}, {lr_final})")
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.lr = float(lr)
        self.lr_final = float(lr_final)
        self.patience = max(1, int(patience))

    @property
    def x(self) -> torch.Tensor:
        return self.param.detach()

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        A, b = problem.A, problem.b
        self.problem = problem
        self.lr0 = self.lr * float(density_scale(A, b).max()) if resume is None else resume["lr0"]
        self.param = x.clone().requires_grad_(True)
        self.opt = torch.optim.Adam([self.param], lr=self.lr0)
        self.halvings, self.stalled, self.best, start = 0, 0, math.inf, 1
        if resume is not None:  # redo iteration resume["iteration"] from the state before its step
            self.opt.load_state_dict(resume["optimizer"])
            self.halvings, self.stalled, self.best = resume["halvings"], resume["stalled"], resume["best"]
            start = resume["iteration"]
        self.pending = False  # the step of the previous iteration is still to take
        return start

    def step(self, it: int) -> None:
        """The step of iteration it - 1 (taken only once its check did not stop the solve),
        then the gradient at the result, which iteration ``it``'s check reports on."""
        if self.pending:
            cosine = 0.5 * (1 + math.cos(math.pi * (it - 1) / self.max_iters))
            self.opt.param_groups[0]["lr"] = (
                self.lr0 * (self.lr_final + (1 - self.lr_final) * cosine) * 0.5**self.halvings
            )
            self.opt.step()
            with torch.no_grad():
                self.param.clamp_(min=0)
        A, b, lam, param = self.problem.A, self.problem.b, self.problem.l1, self.param
        self.opt.zero_grad(set_to_none=True)
        self.r = A.forward(param) - b
        loss = 0.5 * (self.r * self.r).sum() + lam * param.sum()
        loss.backward()
        self.pending = True

    def report(self, it: int) -> dict[str, float]:
        """The gap belongs to this x, before its step."""
        problem, xd, lam = self.problem, self.param.detach(), self.problem.l1
        r = self.r.detach()
        return {**gap_report(problem, xd, r, self.param.grad - lam), "lr": self.opt.param_groups[0]["lr"]}

    def after_check(self, info: dict) -> None:
        if info["objective"] < self.best:
            self.best, self.stalled = info["objective"], 0
        else:
            self.stalled += 1
            if self.stalled >= self.patience:  # oscillating: shrink the step
                self.halvings, self.stalled = self.halvings + 1, 0

    def snapshot(self, it: int) -> dict:
        return {"iteration": it, "x": self.x, "optimizer": self.opt.state_dict(), "lr0": self.lr0,
                "halvings": self.halvings, "stalled": self.stalled, "best": self.best,
                "history": self.history[:-1]}  # this iteration is redone on resume
