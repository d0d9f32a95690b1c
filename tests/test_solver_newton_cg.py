"""newton_cg (projected Newton-CG) against scikit-learn's positive Lasso on a tiny problem."""

from __future__ import annotations

import pytest
import torch

from flamerecon.solvers import Problem, make_solver, resolve_l1
from tests.helpers import csr, objective, sklearn_objective, tiny_problem


@pytest.mark.parametrize("warm_iters", [0, 20], ids=["cold", "fista_warm_start"])
def test_newton_cg_reaches_sklearn_objective(warm_iters):
    A, b, lam = tiny_problem()
    ref = sklearn_objective(A, b, lam)
    problem = Problem(csr(A.astype("float64")), torch.tensor(b).double(), lam)
    res = make_solver("newton_cg", tol=1e-9, max_iters=200, warm_iters=warm_iters,
                      cg_iters=60).solve(problem)
    assert res.converged
    assert (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-7 * ref
    gaps = [h["rel_gap"] for h in res.history]
    assert gaps[-1] < 1e-9 <= gaps[0]


def test_newton_cg_in_float32_reaches_1e_6():
    A, b, lam = tiny_problem(seed=1, C=3)
    ref = sklearn_objective(A, b, lam)
    res = make_solver("newton_cg", tol=1e-6, max_iters=200).solve(
        Problem(csr(A), torch.tensor(b), lam))
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-5 * ref


def test_newton_cg_zero_above_lambda_max_and_time_budget():
    A, b, _ = tiny_problem(seed=6)
    problem = Problem(csr(A), torch.tensor(b))
    problem.l1 = resolve_l1(problem, l1_rel=1.0 + 1e-4)
    assert float(make_solver("newton_cg", tol=1e-6).solve(problem).x.abs().max()) == 0.0
    problem.l1 = resolve_l1(problem, l1_rel=0.05)
    result = make_solver("newton_cg", max_iters=1000, tol=0.0, check_every=5,
                         max_seconds=0.0).solve(problem)
    assert result.iterations == 5 and not result.converged
