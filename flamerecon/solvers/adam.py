"""Adam on the nonnegative LASSO by autograd through the operator's forward (the
differentiable-renderer route: works for any operator whose ``forward`` torch can differentiate,
e.g. the matrix-free projector or :class:`~flamerecon.sparse_ops.CsrOperator`)."""

from __future__ import annotations

import math

import torch

from .base import Callback, Problem, Solver, SolveResult, density_scale, duality_gap, register


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
                 max_seconds: float | None = None, **_: object) -> None:
        if lr <= 0 or lr_final <= 0:
            raise ValueError(f"solver.lr and solver.lr_final must be > 0 (got {lr}, {lr_final})")
        super().__init__(max_iters, tol, check_every, max_seconds)
        self.lr = float(lr)
        self.lr_final = float(lr_final)
        self.patience = max(1, int(patience))

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        A, b, lam = problem.A, problem.b, problem.l1
        resume = self._take_resume()
        lr0 = self.lr * float(density_scale(A, b).max()) if resume is None else resume["lr0"]
        param = x.clone().requires_grad_(True)
        opt = torch.optim.Adam([param], lr=lr0)
        history: list[dict] = []
        converged, it, halvings, stalled, best = False, 0, 0, 0, math.inf
        start = 1
        if resume is not None:  # redo iteration resume["iteration"] from the state before its step
            opt.load_state_dict(resume["optimizer"])
            halvings, stalled, best = resume["halvings"], resume["stalled"], resume["best"]
            history, start = list(resume["history"]), resume["iteration"]
        for it in range(start, self.max_iters + 1):
            opt.zero_grad(set_to_none=True)
            r = A.forward(param) - b
            loss = 0.5 * (r * r).sum() + lam * param.sum()
            loss.backward()
            if it % self.check_every == 0 or it == self.max_iters:
                xd = param.detach()
                primal, gap = duality_gap(problem, xd, r.detach(), param.grad - lam)
                info = {
                    "objective": primal,
                    "data": 0.5 * float((r.detach().double() ** 2).sum()),
                    "l1": lam * float(xd.double().sum()),
                    "gap": gap,
                    "rel_gap": gap / max(primal, 1e-30),
                    "lr": opt.param_groups[0]["lr"],
                }
                if callback is not None:
                    self._state = {
                        "iteration": it, "x": xd, "optimizer": opt.state_dict(), "lr0": lr0,
                        "halvings": halvings, "stalled": stalled, "best": best,
                        "history": list(history),
                    }
                history.append({"iteration": it, **info})
                if callback is not None:
                    callback(it, xd, info)
                if info["rel_gap"] < self.tol or it == self.max_iters or self.out_of_time():
                    converged = info["rel_gap"] < self.tol
                    break  # the gap belongs to this x, before the step
                if primal < best:
                    best, stalled = primal, 0
                else:
                    stalled += 1
                    if stalled >= self.patience:
                        halvings, stalled = halvings + 1, 0  # oscillating: shrink the step
            cosine = 0.5 * (1 + math.cos(math.pi * it / self.max_iters))
            opt.param_groups[0]["lr"] = (
                lr0 * (self.lr_final + (1 - self.lr_final) * cosine) * 0.5**halvings
            )
            opt.step()
            with torch.no_grad():
                param.clamp_(min=0)
        x = param.detach()
        return SolveResult(x, it, 0.0, problem.objective(x), converged, history)
