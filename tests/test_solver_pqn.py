"""pqn (projected L-BFGS) against scikit-learn's positive Lasso on tiny problems; nonnegative,
exact resume from its state, zero above lambda_max."""

from __future__ import annotations

import pytest
import torch

from flamerecon.solvers import Problem, make_solver, resolve_l1
from tests.helpers import (
    assert_columns_solved_alone_alike,
    assert_resumes_exactly,
    csr,
    objective,
    sklearn_objective,
    tiny_problem,
)

pytest.importorskip("sklearn.linear_model")


def test_pqn_reaches_sklearn_objective_in_float64():
    A, b, lam = tiny_problem()
    ref = sklearn_objective(A, b, lam)
    problem = Problem(csr(A.astype("float64")), torch.tensor(b).double(), lam)
    res = make_solver("pqn", tol=1e-9, max_iters=500, check_every=1).solve(problem)
    assert res.converged
    assert (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-9 * ref
    assert res.objective == pytest.approx(objective(A, b, lam, res.x.numpy()), rel=1e-12)


def test_pqn_in_float32_reaches_1e_6_with_each_column_its_own_problem():
    A, b, lam = tiny_problem(seed=1, C=3)
    ref = sklearn_objective(A, b, lam)
    res = make_solver("pqn", tol=1e-6, max_iters=500).solve(Problem(csr(A), torch.tensor(b), lam))
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-6 * ref
    assert_columns_solved_alone_alike("pqn", {"tol": 1e-6, "max_iters": 500}, A, b, lam, res.x, 1e-6 * ref)


def test_pqn_resumes_from_its_state_where_an_uninterrupted_solve_ends():
    A, b, lam = tiny_problem(seed=2, C=3)
    problem = Problem(csr(A), torch.tensor(b), lam)
    assert_resumes_exactly("pqn", {"tol": 0.0, "max_iters": 60, "check_every": 10, "memory": 4}, problem, at=30)


def test_pqn_zero_above_lambda_max_and_refuses_no_memory():
    A, b, _ = tiny_problem(seed=6)
    problem = Problem(csr(A), torch.tensor(b))
    problem.l1 = resolve_l1(problem, l1_rel=1.0 + 1e-4)
    assert float(make_solver("pqn", tol=1e-6).solve(problem).x.abs().max()) == 0.0
    with pytest.raises(ValueError, match="solver.memory"):
        make_solver("pqn", memory=0)
