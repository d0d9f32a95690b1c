"""ssnal (semismooth Newton augmented Lagrangian) against scikit-learn's positive Lasso on tiny
wide and tall problems, nonnegative least squares, its duality-gap certificate, zero above
lambda_max and its refusals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamerecon.solvers import Problem, make_solver, resolve_l1
from flamerecon.solvers.base import duality_gap
from tests.helpers import (
    assert_columns_solved_alone_alike,
    csr,
    objective,
    sklearn_objective,
    tiny_problem,
)

pytest.importorskip("sklearn.linear_model")


@pytest.mark.parametrize("shape", [(80, 60), (40, 120)], ids=["tall", "wide"])
def test_ssnal_reaches_sklearn_objective_in_float64(shape):
    A, b, lam = tiny_problem(N=shape[0], M=shape[1])
    ref = sklearn_objective(A, b, lam)
    problem = Problem(csr(A.astype("float64")), torch.tensor(b).double(), lam)
    res = make_solver("ssnal", tol=1e-10, max_iters=100).solve(problem)
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-9 * ref
    assert res.objective == pytest.approx(objective(A, b, lam, res.x.numpy()), rel=1e-12)
    # the certificate: recomputed from the returned x, the relative gap is below the tolerance
    r = problem.A.forward(res.x) - problem.b
    primal, gap = duality_gap(problem, res.x, r, problem.A.adjoint(r))
    assert gap <= 1e-10 * primal
    gaps = [h["rel_gap"] for h in res.history]
    assert gaps[-1] < 1e-10 <= gaps[0]


@pytest.mark.parametrize("shape", [(80, 60), (40, 120)], ids=["tall", "wide"])
def test_ssnal_in_float32_reaches_1e_6_with_each_column_its_own_problem(shape):
    A, b, lam = tiny_problem(seed=1, N=shape[0], M=shape[1], C=3)
    ref = sklearn_objective(A, b, lam)
    res = make_solver("ssnal", tol=1e-5, max_iters=100).solve(Problem(csr(A), torch.tensor(b), lam))
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-6 * ref
    assert_columns_solved_alone_alike("ssnal", {"tol": 1e-5, "max_iters": 100}, A, b, lam, res.x, 1e-6 * ref)


def test_ssnal_nnls_matches_scipy_nnls():
    from scipy.optimize import nnls

    A, b, _ = tiny_problem(seed=3, N=80, M=40, C=2)
    res = make_solver("ssnal", tol=1e-10, max_iters=200).solve(
        Problem(csr(A.astype("float64")), torch.tensor(b).double(), 0.0))
    assert res.converged
    for c in range(2):
        ref, _ = nnls(A.astype(np.float64), b[:, c].astype(np.float64))
        np.testing.assert_allclose(res.x[:, c].numpy(), ref, atol=1e-6 * np.abs(ref).max())


def test_ssnal_zero_above_lambda_max_and_refuses_bad_options():
    A, b, _ = tiny_problem(seed=6)
    problem = Problem(csr(A), torch.tensor(b))
    problem.l1 = resolve_l1(problem, l1_rel=1.0 + 1e-4)
    assert float(make_solver("ssnal", tol=1e-6).solve(problem).x.abs().max()) == 0.0
    for key, bad in (("sigma", 0.0), ("sigma_growth", 0.5), ("cg_iters", 0), ("newton_iters", 0),
                     ("cg_tol", -1.0), ("sigma_max", 0.0)):
        with pytest.raises(ValueError, match=f"solver.{key}"):
            make_solver("ssnal", **{key: bad})
