"""MART (``solver=mart``) against the textbook: a plain numpy loop of the row-action update on a
tiny problem gives the same iterates; on a consistent nonnegative system it reaches the data;
its blocks of rows share no voxel, so visiting them block by block is the row-by-row order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamerecon.errors import ConfigError
from flamerecon.solvers import Problem, make_solver
from flamerecon.solvers.base import density_scale
from flamerecon.solvers.mart import row_blocks
from tests.helpers import CliRun, csr


def consistent(seed: int = 0, N: int = 40, M: int = 60, C: int = 2, zero_rows: int = 3, density: float = 0.25):
    """A nonnegative sparse A (N, M), fewer rays than voxels as in tomography, and data b = A x
    of a nonnegative x that is 0 on the voxels of ``zero_rows`` rays (their pixels are 0); one
    voxel no ray sees."""
    g = np.random.default_rng(seed)
    A = (g.random((N, M)) * (g.random((N, M)) < density)).astype(np.float32)
    A[:, -1] = 0.0
    x = g.random((M, C)).astype(np.float32)
    x[(A[:zero_rows] > 0).any(0)] = 0.0
    return A, A @ x


def textbook(A: np.ndarray, b: np.ndarray, order: np.ndarray, x: np.ndarray, sweeps: int, relax: float) -> np.ndarray:
    """The row-action MART of the literature, one row at a time, in float64."""
    A, b, x = A.astype(np.float64), b.astype(np.float64), x.astype(np.float64).copy()
    for _ in range(sweeps):
        for i in order:
            a = A[i]
            peak = a.max()
            for c in range(b.shape[1]):
                q = a @ x[:, c]
                if b[i, c] <= 0:
                    x[a > 0, c] = 0.0
                elif q > 0:
                    x[:, c] *= (b[i, c] / q) ** (relax * a / peak)
    return x


@pytest.mark.parametrize("relax", [1.0, 0.5])
def test_mart_is_the_textbook_row_action_update(relax):
    A, b = consistent()
    op = csr(A)
    order = torch.cat(row_blocks(op)).numpy()
    assert sorted(order.tolist()) == list(range(A.shape[0]))  # every row once
    start = np.broadcast_to(density_scale(op, torch.tensor(b)).numpy(), (A.shape[1], b.shape[1])).copy()
    start[(A == 0).all(0)] = 0.0  # a voxel no ray sees keeps no density
    got = make_solver("mart", relax=relax, max_iters=3, tol=0.0).solve(Problem(op, torch.tensor(b))).x.numpy()
    np.testing.assert_allclose(got, textbook(A, b, order, start, 3, relax), rtol=2e-4, atol=1e-7)


def test_the_blocks_share_no_voxel_and_cover_every_row():
    A, _ = consistent(N=200, M=150, density=0.03)  # a few voxels per ray, as a ray through a grid
    blocks = row_blocks(csr(A))
    assert sorted(torch.cat(blocks).tolist()) == [i for i in range(A.shape[0]) if A[i].any()]
    for rows in blocks:
        assert ((A[rows.numpy()] > 0).sum(0) <= 1).all()
    assert len(blocks) < A.shape[0] / 2  # rows do share blocks


@pytest.mark.parametrize("order", ["fixed", "shuffled"])
def test_mart_reaches_the_data_of_a_consistent_nonnegative_system(order):
    A, b = consistent()
    result = make_solver("mart", order=order, max_iters=3000, tol=1e-7).solve(Problem(csr(A), torch.tensor(b)))
    x = result.x.numpy()
    assert (x >= 0).all() and x[-1].max() == 0.0  # the unseen voxel stays empty
    assert np.abs(A @ x - b).max() <= 1e-3 * np.abs(b).max()
    first, last = result.history[0]["residual"], result.history[-1]["residual"]
    assert last < 1e-2 * first


def test_mart_solves_each_colour_as_alone():
    A, b = consistent(C=3)
    both = make_solver("mart", max_iters=5, tol=0.0).solve(Problem(csr(A), torch.tensor(b))).x
    alone = make_solver("mart", max_iters=5, tol=0.0).solve(Problem(csr(A), torch.tensor(b[:, 1:2]))).x
    torch.testing.assert_close(both[:, 1:2], alone, rtol=1e-6, atol=0)


class Dense:
    """A matrix-free operator: products only, no rows."""

    def __init__(self, A: np.ndarray) -> None:
        self.A, self.shape = torch.tensor(A), A.shape

    def forward(self, x):
        return self.A @ x

    def adjoint(self, y):
        return self.A.T @ y


def test_mart_needs_the_operators_rows():
    A, b = consistent()
    with pytest.raises(ConfigError, match=r"solver=mart: .* projector\.backend=assembled"):
        make_solver("mart").solve(Problem(Dense(A), torch.tensor(b)))


@pytest.mark.parametrize("options, words", [
    ({"relax": 1.5}, r"solver\.relax: got 1\.5; MART's relaxation must be > 0 and <= 1"),
    ({"order": "random"}, r"solver\.order: unknown order 'random'"),
])
def test_mart_refuses_options_it_cannot_take(options, words):
    with pytest.raises(ValueError, match=words):
        make_solver("mart", **options)


@pytest.mark.e2e
def test_train_py_reconstructs_with_mart(tmp_path):
    result = CliRun(tmp_path / "run", "solver=mart", "solver.max_iters=10", "log.eval_every=0").result()
    assert result.returncode == 0, result.stderr
    assert "mart" in result.stdout and (tmp_path / "run" / "density.npz").is_file()


def test_rays_that_share_voxels_too_densely_are_refused_not_swept_one_by_one():
    A = np.ones((4100, 3), np.float32)  # every ray through every voxel: one ray a block
    with pytest.raises(ConfigError, match=r"solver=mart: the rays share voxels too densely .* use a finer grid"):
        make_solver("mart").solve(Problem(csr(A), torch.ones(4100, 1)))
