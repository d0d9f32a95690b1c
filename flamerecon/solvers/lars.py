"""The paper's solver: nonnegative LARS-LASSO, the exact homotopy path from lambda_max down to
the problem's lambda (Efron et al. 2004), via scikit-learn's ``lars_path_gram``.

The path works on the dense M x M Gram matrix A^T A, so it only suits small problems (a few
thousand hull voxels); larger ones are refused with a pointer to ``fista``.
"""

from __future__ import annotations

import torch

from flamerecon import interrupt
from flamerecon.solvers.base import Callback, LinearOperator, Problem, Solver, SolveResult, register


def gram_matrix(A: LinearOperator, like: torch.Tensor, block: int = 256) -> torch.Tensor:
    """A^T A (M, M) float64 on the CPU, built block by block through forward/adjoint.

    ``like`` gives the dtype and device the operator works in.
    """
    M = A.shape[1]
    G = torch.empty(M, M, dtype=torch.float64)
    for j0 in range(0, M, block):
        j1 = min(M, j0 + block)
        E = torch.zeros(M, j1 - j0, dtype=like.dtype, device=like.device)
        E[torch.arange(j0, j1), torch.arange(j1 - j0)] = 1
        G[:, j0:j1] = A.adjoint(A.forward(E)).double().cpu()
    return 0.5 * (G + G.T)


def too_many_voxels(M: int, max_voxels: int) -> str | None:
    """Why LARS refuses a problem of ``M`` unknowns (hull voxels) under ``solver.max_voxels``,
    or None where it takes it: the run checks this before any work, the solver again."""
    if M <= max_voxels:
        return None
    return (f"solver=lars: the problem has {M} unknowns (hull voxels), more than solver.max_voxels={max_voxels}; "
            f"the LARS path needs the dense {M}x{M} Gram matrix ({8 * M * M / 1e9:.1f} GB) and up to {M} steps. "
            "Use solver=fista (the exact default) for problems this size, or a smaller grid.resolution")


@register("lars")
class Lars(Solver):
    """Nonnegative LARS-LASSO per channel, exact at the problem's lambda.

    Refuses problems with more than ``max_voxels`` unknowns (the Gram matrix costs 8 M^2
    bytes and the path up to M steps). A warm start is ignored: the path starts at lambda_max.
    """

    def __init__(self, max_voxels: int = 5000, max_iters: int | None = None) -> None:
        self.max_voxels = int(max_voxels)
        self.max_iters = None if max_iters is None else int(max_iters)

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        try:
            from sklearn.linear_model import lars_path_gram
        except ImportError as err:  # pragma: no cover - depends on the environment
            raise RuntimeError("solver=lars needs scikit-learn (pip install scikit-learn); "
                               "solver=fista solves the same problem without it") from err
        A, b = problem.A, problem.b
        N, M = A.shape
        refusal = too_many_voxels(M, self.max_voxels)
        if refusal is not None:
            raise ValueError(refusal)
        G = gram_matrix(A, b).numpy()
        Xy = A.adjoint(b).double().cpu().numpy()
        max_iter = self.max_iters if self.max_iters is not None else 10 * M + 10
        cols, steps, converged = [], 0, True
        for c in range(b.shape[1]):
            interrupt.check()
            _, _, coef, n_iter = lars_path_gram(
                Xy[:, c], G, n_samples=N, alpha_min=problem.l1 / N, method="lasso",
                positive=True, max_iter=max_iter, return_path=False, return_n_iter=True,
            )
            cols.append(torch.as_tensor(coef))
            steps = max(steps, int(n_iter))
            converged &= n_iter < max_iter
        x = torch.stack(cols, 1).to(dtype=b.dtype, device=b.device).clamp_min(0)
        parts = problem.objective_parts(x)
        history = [{"iteration": steps, **parts}]
        if callback is not None:
            callback(steps, x, parts)
        return SolveResult(x, steps, 0.0, parts["objective"], converged, history)
