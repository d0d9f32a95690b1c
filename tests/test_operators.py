"""Every operator the package ships through the same conformance checks: the shapes of forward
and adjoint, the dot test that proves the adjoint (:func:`flamerecon.operators.dottest`), and
the operator norm, cached, against the largest singular value of the dense matrix."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import (
    HullGradient,
    StackedOperator,
    dottest,
    hull_gradient,
    norm,
    norm_sq,
)
from flamerecon.operators.base import COSTLY_NORM_ITERS, collatz_wielandt_bound
from flamerecon.operators.projector import make_operator
from flamerecon.solvers import Problem, make_solver
from tests.helpers import csr, random_coo, random_hull, random_rays, tiny_problem

GRID = (3, 3, 3)  # nz, ny, nx
HULL = torch.tensor([i for i in range(27) if i not in (0, 8, 13, 26)])  # holes break neighbours
BOX = VoxelGrid.from_box((-0.3, 0.2, 1.0), (0.7, 1.7, 1.75), (8, 12, 6))  # conftest's box_grid


def projector(backend: str):
    return make_operator(backend, BOX, random_rays(BOX, 300), random_hull(BOX))


def stacked():
    A = np.random.default_rng(0).random((40, len(HULL))).astype(np.float32)
    return StackedOperator(csr(A), hull_gradient(GRID, HULL), 0.5)


#: name -> (build the operator, dtype of its vectors, rtol of its dot test)
OPERATORS = {
    "assembled": (lambda: projector("assembled"), torch.float32, 1e-5),
    "matrix_free": (lambda: projector("matrix_free"), torch.float32, 1e-5),
    "csr": (lambda: random_coo(seed=1)[0], torch.float32, 1e-5),
    "hull_gradient": (lambda: hull_gradient(GRID, HULL), torch.float32, 1e-5),
    "hull_gradient_per_voxel": (lambda: HullGradient(GRID, HULL), torch.float64, 1e-12),
    "stacked": (stacked, torch.float32, 1e-5),
}


def dense(op, dtype) -> torch.Tensor:
    """The operator as a dense (rows, M) float64 matrix, column by column."""
    eye = torch.eye(op.shape[1], dtype=dtype)
    return op.forward(eye).reshape(-1, op.shape[1]).double()


@pytest.mark.parametrize("name", list(OPERATORS))
def test_every_operator_passes_the_dot_test(name):
    build, dtype, rtol = OPERATORS[name]
    op = build()
    N, M = op.shape
    g = torch.Generator().manual_seed(1)
    x = torch.rand(M, 3, generator=g, dtype=dtype)
    Ax = op.forward(x)
    y = torch.randn(Ax.shape, generator=g, dtype=dtype)  # nonzero everywhere
    ATy = op.adjoint(y)
    assert Ax.numel() == N * 3 and Ax.shape[-1] == 3 and ATy.shape == (M, 3)
    assert float((Ax.double() ** 2).sum()) > 0  # the operator does see the unknowns
    lhs, rhs = dottest(op, x, y, rtol=rtol)
    assert lhs == pytest.approx(rhs, rel=rtol)
    dottest(op, dtype=dtype, rtol=rtol)  # and on its own random vectors


def test_the_dot_test_catches_a_wrong_adjoint():
    op = random_coo(seed=1)[0]

    class Transposed:  # A^T with A's forward as its adjoint: right shapes, wrong adjoint
        shape = (op.shape[1], op.shape[0])
        forward, adjoint = op.adjoint, lambda self, y: 2.0 * op.forward(y)

    with pytest.raises(ValueError, match=r"dottest: <A x, y> = .* the adjoint is not that of forward"):
        dottest(Transposed())


@pytest.mark.parametrize("name", list(OPERATORS))
def test_the_norm_is_the_largest_singular_value_and_is_computed_once(name):
    build, dtype, _ = OPERATORS[name]
    op = build()
    costly = getattr(op, "costly_products", False)
    calls = []  # products of A^T A: an adjoint, or one pass of the operator's fused residual and gradient
    adjoint, fused = op.adjoint, getattr(op, "residual_gradient", None)
    op.adjoint = lambda y: (calls.append(1), adjoint(y))[1]
    if fused is not None:
        op.residual_gradient = lambda x, b: (calls.append(1), fused(x, b))[1]
    first = norm_sq(op, dtype=dtype)
    products = len(calls)
    assert products == COSTLY_NORM_ITERS if costly else 1 < products <= 30  # Lanczos stops when converged
    assert norm_sq(op, dtype=dtype) == first and norm(op, dtype=dtype) == first**0.5
    assert len(calls) == products  # one estimate, then the cache
    norm_sq(op, dtype=dtype, iters=31)  # another estimate (its value may agree to the last bit)
    assert len(calls) == 2 * products
    op.adjoint = adjoint
    if fused is not None:
        op.residual_gradient = fused
    exact = float(torch.linalg.matrix_norm(dense(op, dtype), 2)) ** 2
    if costly:  # a bound from above, for a safe step, within 10% after three products of A^T A
        assert exact * (1 - 1e-5) <= first <= 1.1 * exact
    else:  # Lanczos approaches ||A||^2 from below, here to float precision
        assert exact * (1 - 1e-4) <= first <= exact * (1 + 1e-5)


@pytest.mark.parametrize("seed", range(5))
def test_the_collatz_wielandt_bound_is_above_the_norm_and_tightens(seed):
    op = random_coo(seed=seed)[0]  # nonnegative entries
    exact = float(torch.linalg.matrix_norm(dense(op, torch.float32), 2)) ** 2
    bounds = [collatz_wielandt_bound(op, iters=k) for k in (1, 2, 4, 40)]
    assert all(b >= exact * (1 - 1e-5) for b in bounds)
    assert all(a >= b * (1 - 1e-6) for a, b in itertools.pairwise(bounds))  # never looser
    assert bounds[-1] <= exact * 1.01


@pytest.mark.parametrize("name", ["fista", "tv"])
def test_a_second_solve_on_the_same_operator_reuses_its_norm(name):
    A, b, lam = tiny_problem()
    op = csr(A)
    calls = []
    adjoint, fused = op.adjoint, op.residual_gradient
    op.adjoint = lambda y: (calls.append(1), adjoint(y))[1]
    op.residual_gradient = lambda x, b: (calls.append(1), fused(x, b))[1]
    problem = Problem(op, torch.tensor(b), lam, grid_shape=(3, 4, 5),
                      voxel_index=torch.arange(A.shape[1]))
    counts, results = [], []
    for _ in range(2):
        before = len(calls)
        results.append(make_solver(name, max_iters=20, tol=0.0).solve(problem))
        counts.append(len(calls) - before)
    fresh, norm_products = csr(A), []
    fresh_adjoint, fresh_fused = fresh.adjoint, fresh.residual_gradient
    fresh.adjoint = lambda y: (norm_products.append(1), fresh_adjoint(y))[1]
    fresh.residual_gradient = lambda x, b: (norm_products.append(1), fresh_fused(x, b))[1]
    norm_sq(fresh)
    assert counts[0] - counts[1] == len(norm_products) > 1  # the norm, computed by the first solve only
    assert torch.equal(results[0].x, results[1].x)
