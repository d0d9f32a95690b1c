"""The smoothness-aware solver against scipy's L-BFGS-B on the same objective."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from flamerecon.operators import CsrOperator, hull_gradient
from flamerecon.solvers import Problem, make_solver

scipy_optimize = pytest.importorskip("scipy.optimize")

GRID = (2, 3, 4)  # nz, ny, nx
HULL = np.array([i for i in range(24) if i not in (5, 6, 17, 23)])  # holes break neighbours


def reference_gradient(grid_shape, hull) -> np.ndarray:
    """D by explicit loops over voxel pairs (independent of the vectorised builder)."""
    nz, ny, nx = grid_shape
    col = {int(v): m for m, v in enumerate(hull)}
    rows = []
    for k, j, i in itertools.product(range(nz), range(ny), range(nx)):
        here = (k * ny + j) * nx + i
        for dk, dj, di in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            kk, jj, ii = k + dk, j + dj, i + di
            if kk < nz and jj < ny and ii < nx:
                there = (kk * ny + jj) * nx + ii
                if here in col and there in col:
                    row = np.zeros(len(hull))
                    row[col[there]], row[col[here]] = 1.0, -1.0
                    rows.append(row)
    return np.array(rows)


def test_hull_gradient_links_only_neighbouring_hull_voxels():
    D = hull_gradient(GRID, torch.tensor(HULL)).A.to_dense().numpy()
    ref = reference_gradient(GRID, HULL)
    key = lambda m: sorted(map(tuple, m))
    assert key(D) == key(ref)


@pytest.mark.parametrize("name", ["fista_smooth", "pqn_smooth"])
def test_smooth_solvers_match_lbfgsb(name):
    g = np.random.default_rng(0)
    M, N, C = len(HULL), 30, 2
    A = (g.random((N, M)) * (g.random((N, M)) < 0.4)).astype(np.float32)
    b = (A @ g.random((M, C)) + 0.05 * g.standard_normal((N, C))).astype(np.float32)
    lam = 0.02 * float((A.T @ b).max())
    r, c = np.nonzero(A)
    op = CsrOperator.from_coo(torch.tensor(r), torch.tensor(c), torch.tensor(A[r, c]), (N, M))
    problem = Problem(op, torch.tensor(b), lam, grid_shape=GRID, voxel_index=torch.tensor(HULL))
    res = make_solver(name, smooth=0.2, tol=1e-5, max_iters=5000).solve(problem)
    s = res.history[-1]["smooth_weight"]
    assert s > 0

    D = reference_gradient(GRID, HULL)
    A64, b64 = A.astype(np.float64), b.astype(np.float64)

    def f(z):
        x = z.reshape(M, C)
        r, d = A64 @ x - b64, D @ x
        val = 0.5 * (r**2).sum() + 0.5 * s * (d**2).sum() + lam * x.sum()
        return val, (A64.T @ r + s * D.T @ d + lam).ravel()

    ref = scipy_optimize.minimize(f, np.zeros(M * C), jac=True, method="L-BFGS-B",
                                  bounds=[(0, None)] * (M * C),
                                  options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10_000})
    ours = f(res.x.double().numpy().ravel())[0]
    assert res.converged and (res.x >= 0).all()
    assert abs(ours - ref.fun) <= 1e-4 * ref.fun
    assert res.objective == pytest.approx(ours, rel=1e-5)
    # the penalty changes the answer: plain fista lands elsewhere
    plain = make_solver("fista", tol=1e-5, max_iters=5000).solve(problem)
    assert f(plain.x.double().numpy().ravel())[0] > ref.fun * (1 + 1e-3)


@pytest.mark.parametrize("name", ["fista_smooth", "pqn_smooth"])
def test_smooth_solvers_need_hull_geometry(name):
    op = CsrOperator.from_coo(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), (1, 1))
    with pytest.raises(ValueError, match=f"solver={name} needs.*grid_shape"):
        make_solver(name).solve(Problem(op, torch.ones(1, 1)))
