"""Tiny nonnegative LASSO problems and their references, for the solver and operator tests."""

from __future__ import annotations

import numpy as np
import torch

from flamerecon.operators import CsrOperator


def tiny_problem(seed: int = 0, N: int = 80, M: int = 60, C: int = 2, rel: float = 0.05):
    """A nonnegative sparse A (N, M), sparse nonnegative truth, noisy b (N, C), lambda."""
    g = np.random.default_rng(seed)
    A = (g.random((N, M)) * (g.random((N, M)) < 0.3)).astype(np.float32)
    truth = (g.random((M, C)) * (g.random((M, C)) < 0.3)).astype(np.float32)
    b = A @ truth + 0.01 * g.standard_normal((N, C)).astype(np.float32)
    lam = rel * float(np.abs(A.T @ b).max())
    return A, b, lam


def csr(A: np.ndarray) -> CsrOperator:
    r, c = np.nonzero(A)
    return CsrOperator.from_coo(torch.tensor(r), torch.tensor(c), torch.tensor(A[r, c]), A.shape)


def objective(A: np.ndarray, b: np.ndarray, lam: float, x: np.ndarray) -> float:
    A, b, x = A.astype(np.float64), b.astype(np.float64), x.astype(np.float64)
    return float(0.5 * ((A @ x - b) ** 2).sum() + lam * np.abs(x).sum())


def sklearn_objective(A: np.ndarray, b: np.ndarray, lam: float) -> float:
    """scikit-learn minimises (1/2N)||b - A w||^2 + alpha ||w||_1: alpha = lam / N."""
    from sklearn.linear_model import Lasso

    lasso = Lasso(alpha=lam / A.shape[0], positive=True, fit_intercept=False, tol=1e-12,
                  max_iter=100_000)
    lasso.fit(A.astype(np.float64), b.astype(np.float64))
    return objective(A, b, lam, lasso.coef_.T.reshape(A.shape[1], -1))


def assert_columns_solved_alone_alike(name: str, options: dict, A: np.ndarray, b: np.ndarray, lam: float,
                                      x: torch.Tensor, tolerance: float) -> None:
    """Solver ``name`` with ``options`` on column 1 of ``b`` alone reaches, within ``tolerance``,
    the objective of column 1 of ``x`` (that column of a solve of every column)."""
    from flamerecon.solvers import Problem, make_solver

    alone = make_solver(name, **options).solve(Problem(csr(A), torch.tensor(b[:, 1:2]), lam))
    assert abs(objective(A, b[:, 1:2], lam, alone.x.numpy())
               - objective(A, b[:, 1:2], lam, x[:, 1:2].numpy())) <= tolerance


def random_coo(seed: int = 0, N: int = 50, M: int = 40, nnz: int = 300):
    """A CsrOperator from random COO triplets with duplicates, and its dense (N, M) matrix."""
    g = np.random.default_rng(seed)
    rows, cols = g.integers(0, N, nnz), g.integers(0, M, nnz)  # duplicates on purpose
    vals = g.random(nnz).astype(np.float32)
    dense = np.zeros((N, M), np.float32)
    np.add.at(dense, (rows, cols), vals)
    op = CsrOperator.from_coo(torch.tensor(rows), torch.tensor(cols), torch.tensor(vals), (N, M))
    return op, dense


def assert_resumes_exactly(name: str, options: dict, problem, at: int) -> None:
    """Solver ``name`` stopped at iteration ``at`` (its :meth:`state` kept) and resumed from
    that state ends where the uninterrupted solve ends: same iterations, iterate and history."""
    import copy

    from flamerecon.solvers import make_solver

    full = make_solver(name, **options).solve(problem)
    saved = {}

    def keep(it, x, info):
        if it == at:
            saved.update(copy.deepcopy(solver.state()))

    solver = make_solver(name, **options)
    solver.solve(problem, callback=keep)
    resumed = make_solver(name, **options)
    resumed.load_state(saved)
    again = resumed.solve(problem, x0=saved["x"])
    assert again.iterations == full.iterations == options["max_iters"]
    assert torch.equal(again.x, full.x)
    assert [e["iteration"] for e in again.history] == [e["iteration"] for e in full.history]
