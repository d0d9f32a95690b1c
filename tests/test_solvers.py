"""Every solver against an independent reference on tiny problems (scikit-learn, scipy)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from flamerecon.solvers import Problem, make_solver
from tests.helpers import csr, objective, sklearn_objective, tiny_problem

pytest.importorskip("sklearn.linear_model")


@pytest.fixture(scope="module")
def lasso_case():
    A, b, lam = tiny_problem()
    return A, b, lam, sklearn_objective(A, b, lam)


@pytest.mark.slow
def test_fista_reaches_sklearn_objective(lasso_case):
    A, b, lam, ref = lasso_case
    res = make_solver("fista", tol=1e-5, max_iters=5000).solve(Problem(csr(A), torch.tensor(b), lam))
    assert res.converged
    assert (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-4 * ref


@pytest.mark.slow
def test_adam_reaches_sklearn_objective(lasso_case):
    A, b, lam, ref = lasso_case
    problem = Problem(csr(A), torch.tensor(b), lam)
    res = make_solver("adam", tol=1e-9, max_iters=2000).solve(problem)
    assert (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-3 * ref
    # and the objective it reports is the one it reached
    assert res.objective == pytest.approx(objective(A, b, lam, res.x.numpy()), rel=1e-5)


def test_lars_matches_sklearn_at_the_same_lambda(lasso_case):
    A, b, lam, ref = lasso_case
    res = make_solver("lars").solve(Problem(csr(A), torch.tensor(b), lam))
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-4 * ref


def test_lars_refuses_large_problems_and_names_fista():
    A, b, lam = tiny_problem()
    with pytest.raises(ValueError, match="solver=fista"):
        make_solver("lars", max_voxels=10).solve(Problem(csr(A), torch.tensor(b), lam))


@pytest.mark.parametrize("shape", [(80, 30), (30, 60)], ids=["overdetermined", "underdetermined"])
def test_cgls_matches_scipy_lsqr(shape):
    from scipy.sparse.linalg import lsqr

    A, b, _ = tiny_problem(seed=2, N=shape[0], M=shape[1], C=2)
    A += np.eye(*A.shape, dtype=np.float32)  # well conditioned, full rank
    res = make_solver("cgls", tol=1e-7, max_iters=500).solve(Problem(csr(A), torch.tensor(b)))
    ref = np.stack([lsqr(A.astype(np.float64), b[:, c].astype(np.float64),
                         atol=1e-14, btol=1e-14, iter_lim=10_000)[0] for c in range(2)], 1)
    np.testing.assert_allclose(res.x.numpy(), ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max())


def test_cgls_damped_matches_scipy_lsqr_damp():
    from scipy.sparse.linalg import lsqr

    A, b, _ = tiny_problem(seed=3, N=40, M=60, C=1)
    res = make_solver("cgls", tol=1e-7, damp=0.5, max_iters=500).solve(
        Problem(csr(A), torch.tensor(b)))
    ref = lsqr(A.astype(np.float64), b[:, 0].astype(np.float64), damp=0.5,
               atol=1e-14, btol=1e-14)[0]
    np.testing.assert_allclose(res.x[:, 0].numpy(), ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max())


def test_sart_decreases_residual_monotonically_on_consistent_system():
    A, _, _ = tiny_problem(seed=4, N=90, M=60, C=2)
    truth = np.random.default_rng(4).random((60, 2)).astype(np.float32)
    b = A @ truth  # consistent, with a nonnegative solution
    weighted, plain = [], []
    res = make_solver("sart", relax=1.5, tol=0.0, max_iters=100, check_every=1).solve(
        Problem(csr(A), torch.tensor(b)),
        callback=lambda it, x, info: (weighted.append(info["weighted_residual"]),
                                      plain.append(info["data"])))
    assert (res.x >= 0).all()
    start = 0.5 * float((b.astype(np.float64) ** 2 / A.sum(1, keepdims=True)).sum())  # x = 0
    assert all(a2 <= a1 for a1, a2 in itertools.pairwise([start, *weighted]))
    assert plain[-1] < 1e-2 * plain[0]


def test_sart_stops_on_its_tolerance_not_at_its_first_check():
    A, _, _ = tiny_problem(seed=4, N=90, M=60, C=2)
    b = A @ np.random.default_rng(4).random((60, 2)).astype(np.float32)
    problem = Problem(csr(A), torch.tensor(b))
    tight = make_solver("sart", tol=1e-6, max_iters=400, check_every=10).solve(problem)
    loose = make_solver("sart", tol=1e-1, max_iters=400, check_every=10).solve(problem)
    assert 10 < loose.iterations < tight.iterations  # the first check has nothing to compare


def test_make_solver_lists_choices_for_unknown_name():
    with pytest.raises(ValueError, match="unknown solver 'nope'"):
        make_solver("nope")


def test_resolve_l1_absolute_and_relative():
    from flamerecon.solvers import resolve_l1

    A, b, _ = tiny_problem(seed=5)
    op, bt = csr(A), torch.tensor(b)
    assert resolve_l1(op, bt, l1=0.3) == 0.3
    assert resolve_l1(op, bt, l1=0.0, l1_rel=1e-2) == pytest.approx(1e-2 * (A.T @ b).max(),
                                                                     rel=1e-5)
    assert resolve_l1(Problem(op, bt), l1=None, l1_rel=0.5) == pytest.approx(
        0.5 * (A.T @ b).max(), rel=1e-5)
    with pytest.raises(ValueError, match="solver.l1_rel"):
        resolve_l1(op, bt, l1=0.3, l1_rel=0.1)
    with pytest.raises(ValueError, match="solver.l1 must be"):
        resolve_l1(op, bt, l1=-1.0)


def test_lambda_at_l1_rel_one_gives_zero_solution():
    from flamerecon.solvers import resolve_l1

    A, b, _ = tiny_problem(seed=6)
    problem = Problem(csr(A), torch.tensor(b))
    problem.l1 = resolve_l1(problem, l1_rel=1.0 + 1e-4)
    res = make_solver("fista", tol=1e-6).solve(problem)
    assert float(res.x.abs().max()) == 0.0


def test_lbfgsb_reaches_sklearn_objective(lasso_case):
    A, b, lam, ref = lasso_case
    res = make_solver("lbfgsb", tol=1e-6, max_iters=2000, check_every=5).solve(
        Problem(csr(A), torch.tensor(b), lam))
    assert (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-4 * ref


@pytest.mark.parametrize("name", ["fista", "fista_smooth", "tv", "lbfgsb", "pqn", "pqn_smooth",
                                  "adam", "cgls", "sart", "ssnal", "mart"])
def test_every_iterative_solver_stops_at_the_first_check_past_its_time_budget(name):
    """max_seconds=0 is spent before the first check: the solve ends there, unconverged."""
    A, b, lam = tiny_problem()
    problem = Problem(csr(A), torch.tensor(b), lam, grid_shape=(3, 4, 5),
                      voxel_index=torch.arange(A.shape[1]))
    result = make_solver(name, max_iters=1000, tol=0.0, check_every=5, max_seconds=0.0).solve(problem)
    assert result.iterations == 5 and not result.converged
