"""FISTA without the L1 term is nonnegative least squares: it must still stop on its own."""

import numpy as np
import torch
from scipy.optimize import nnls

from flamerecon.solvers import Problem, make_solver


class Dense:
    def __init__(self, A: torch.Tensor):
        self.A, self.shape = A, tuple(A.shape)

    def forward(self, x):
        return self.A @ x

    def adjoint(self, y):
        return self.A.T @ y


def test_fista_with_l1_zero_converges_to_scipy_nnls():
    g = torch.Generator().manual_seed(0)
    A = torch.rand(80, 40, generator=g, dtype=torch.float64)
    b = torch.rand(80, 2, generator=g, dtype=torch.float64)
    problem = Problem(Dense(A), b, 0.0)
    result = make_solver("fista", max_iters=20000, tol=1e-8).solve(problem)
    assert result.converged and result.iterations < 20000
    ref = np.stack([nnls(A.numpy(), b[:, c].numpy())[0] for c in range(2)], 1)
    ref_obj = problem.objective(torch.from_numpy(ref))
    assert abs(result.objective - ref_obj) <= 1e-6 * ref_obj
