"""solver=tv (nonnegative LASSO + isotropic 3D TV on the hull) against independent references:
the dual problem solved by scipy's SLSQP, scikit-learn's Lasso at tv = 0, a piecewise-constant
phantom it should recover better than L1 alone, exact resume, bad weights, the command line."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing import event_accumulator as ea
from tensorboard.plugins.hparams import plugin_data_pb2

from flamerecon.errors import ConfigError, Interrupted
from flamerecon.operators import HullGradient, hull_gradient
from flamerecon.run.pipeline import reconstruct
from flamerecon.solvers import Problem, make_solver
from tests.helpers import (
    FAST,
    REPO,
    TINY,
    assert_resumes_exactly,
    csr,
    interrupt_at,
    objective,
    sklearn_objective,
    tiny_cfg,
    tiny_problem,
)

scipy_optimize = pytest.importorskip("scipy.optimize")

GRID = (3, 3, 3)  # nz, ny, nx
HULL = np.array([i for i in range(27) if i not in (0, 8, 13, 26)])  # holes break neighbours


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny solves on one thread: torch's sparse products fork threads however small the matrix,
    and on a busy shared machine that made this file 5x slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def grouped_differences(grid_shape, hull) -> tuple[np.ndarray, np.ndarray]:
    """Forward differences (E, M) by explicit loops, and the voxel (E,) each row belongs to."""
    nz, ny, nx = grid_shape
    col = {int(v): m for m, v in enumerate(hull)}
    rows, owner = [], []
    for k, j, i in itertools.product(range(nz), range(ny), range(nx)):
        here = (k * ny + j) * nx + i
        for dk, dj, di in ((0, 0, 1), (0, 1, 0), (1, 0, 0)):
            kk, jj, ii = k + dk, j + dj, i + di
            there = (kk * ny + jj) * nx + ii
            if kk < nz and jj < ny and ii < nx and here in col and there in col:
                row = np.zeros(len(hull))
                row[col[there]], row[col[here]] = 1.0, -1.0
                rows.append(row)
                owner.append(col[here])
    return np.array(rows), np.array(owner)


def isotropic_tv(D: np.ndarray, owner: np.ndarray, x: np.ndarray) -> float:
    d = D @ x  # (E, C)
    sq = np.zeros((x.shape[0], x.shape[1]))
    np.add.at(sq, owner, d**2)
    return float(np.sqrt(sq).sum())


def dual_reference(A, b, lam, mu, D, owner) -> float:
    """The optimum of the Fenchel dual, per channel, by SLSQP (smooth constraints only):

        max_{u, y}  -0.5||u||^2 - <u, b>   s.t.  A^T u + D^T y >= -lam,  ||y_m|| <= mu,

    equal to the primal optimum by strong duality (a linear term plus a norm, Slater holds).
    ``lam`` and ``mu`` are numbers or per-voxel weights (M, C) (the reweighted objective)."""
    N, E, M = A.shape[0], D.shape[0], A.shape[1]
    A, total = A.astype(np.float64), 0.0
    lam_all = np.broadcast_to(np.asarray(lam, np.float64), (M, b.shape[1]))
    mu_all = np.broadcast_to(np.asarray(mu, np.float64), (M, b.shape[1]))
    groups = [(m, np.nonzero(owner == m)[0]) for m in range(M) if (owner == m).any()]
    for c in range(b.shape[1]):
        bc, lam_c = b[:, c].astype(np.float64), lam_all[:, c]
        cons = [{"type": "ineq", "fun": lambda z, lam_c=lam_c: lam_c + A.T @ z[:N] + D.T @ z[N:],
                 "jac": lambda z: np.hstack([A.T, D.T])}]
        for m, g in groups:
            def jac(z, g=g):
                J = np.zeros((1, N + E))
                J[0, N + g] = -2.0 * z[N + g]
                return J
            cons.append({"type": "ineq", "fun": lambda z, g=g, r=mu_all[m, c]: np.array([r**2 - (z[N + g] ** 2).sum()]),
                         "jac": jac})

        def f(z, bc=bc):
            return 0.5 * z[:N] @ z[:N] + z[:N] @ bc, np.concatenate([z[:N] + bc, np.zeros(E)])

        res = scipy_optimize.minimize(
            f, np.zeros(N + E), jac=True, method="SLSQP", constraints=cons,
            options={"ftol": 1e-15, "maxiter": 2000})
        total -= res.fun
    return total


@pytest.fixture(scope="module")
def tv_case():
    """A random nonnegative A (40, M) on the holed 3x3x3 hull, a two-level truth, noisy b."""
    g = np.random.default_rng(0)
    M, N, C = len(HULL), 40, 2
    A = (g.random((N, M)) * (g.random((N, M)) < 0.4)).astype(np.float32)
    truth = np.zeros((M, C))
    truth[: M // 2] = 1.0
    truth[M // 2:, 1] = 0.5
    b = (A @ truth + 0.05 * g.standard_normal((N, C))).astype(np.float32)
    lmax = float((A.T @ b).max())
    problem = Problem(csr(A), torch.tensor(b), 0.01 * lmax, grid_shape=GRID,
                      voxel_index=torch.tensor(HULL))
    return A, b, problem, lmax


def test_hull_gradient_per_voxel_matches_the_loop():
    D, owner = grouped_differences(GRID, HULL)
    grad = HullGradient(GRID, torch.tensor(HULL))
    x = torch.rand(len(HULL), 2, dtype=torch.float64)
    d = grad.forward(x)  # (3, M, 2)
    stacked = np.concatenate([d[a].numpy() for a in range(3)])  # rows of all voxels, per axis
    present = np.zeros((3, len(HULL)), bool)
    for row, m in zip(D, owner):
        axis = {1: 0, 3: 1, 9: 2}[int(HULL[np.argmax(row)] - HULL[m])]
        present[axis, m] = True
        np.testing.assert_allclose(d[axis, m].numpy(), row @ x.numpy())
    assert np.abs(stacked[~present.reshape(-1)]).max() == 0  # no difference across the boundary
    assert present.sum() == hull_gradient(GRID, torch.tensor(HULL)).shape[0]
    # its adjoint: the dot test in test_operators.py


def test_tv_reaches_the_dual_optimum_of_scipy(tv_case):
    A, b, problem, lmax = tv_case
    res = make_solver("tv", tv=0.05, tol=1e-5, max_iters=20_000).solve(problem)
    assert res.converged and (res.x >= 0).all()
    D, owner = grouped_differences(GRID, HULL)
    mu = 0.05 * lmax
    ours = objective(A, b, problem.l1, res.x.numpy()) + mu * isotropic_tv(D, owner, res.x.double().numpy())
    ref = dual_reference(A, b, problem.l1, mu, D, owner)
    assert abs(ours - ref) <= 1e-4 * ref
    assert res.objective == pytest.approx(ours, rel=1e-5)
    last = res.history[-1]
    assert last["tv_weight"] == pytest.approx(mu, rel=1e-6)
    assert last["objective"] == pytest.approx(last["data"] + last["l1"] + last["tv"], rel=1e-9)
    # the penalty matters here: the plain LASSO solution costs more under this objective
    lasso = make_solver("fista", tol=1e-5, max_iters=5000).solve(problem).x
    assert objective(A, b, problem.l1, lasso.numpy()) + mu * isotropic_tv(
        D, owner, lasso.double().numpy()) > ref * (1 + 1e-3)


def test_tv_zero_is_the_nonnegative_lasso_of_sklearn():
    A, b, lam = tiny_problem()  # M = 60 voxels: a full 3 x 4 x 5 grid
    problem = Problem(csr(A), torch.tensor(b), lam, grid_shape=(3, 4, 5),
                      voxel_index=torch.arange(60))
    res = make_solver("tv", tv=0.0, tol=1e-5, max_iters=20_000).solve(problem)
    ref = sklearn_objective(A, b, lam)
    assert res.converged and (res.x >= 0).all()
    assert abs(objective(A, b, lam, res.x.numpy()) - ref) <= 1e-4 * ref
    assert res.history[-1]["tv"] == 0.0


def few_projections(n: int) -> np.ndarray:
    """Parallel projections of an n^3 grid (x fastest): sums along z, y, x and along both
    diagonals of every z slice, (3 n^2 + 2 n (2n - 1), n^3)."""
    idx = np.arange(n**3).reshape(n, n, n)  # [k, j, i]
    rows = [idx[:, j, i] for j in range(n) for i in range(n)]
    rows += [idx[k, :, i] for k in range(n) for i in range(n)]
    rows += [idx[k, j, :] for k in range(n) for j in range(n)]
    rows += [np.diagonal(face, s) for k in range(n) for face in (idx[k], idx[k][:, ::-1])
             for s in range(1 - n, n)]
    A = np.zeros((len(rows), n**3), np.float32)
    for r, cells in enumerate(rows):
        A[r, cells] = 1.0
    return A


def test_tv_recovers_a_piecewise_constant_phantom_better_than_l1_alone():
    n = 8
    k, j, i = np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij")
    truth = ((k - 4) ** 2 + (j - 4) ** 2 + (i - 4) ** 2 < 3.2**2).astype(float)  # a ball
    truth[(k - 3) ** 2 + (j - 5) ** 2 + (i - 3.5) ** 2 < 1.6**2] = 0.4  # with a darker core
    x_true = truth.reshape(-1, 1)
    A = few_projections(n)  # 432 rays for 512 unknowns
    g = np.random.default_rng(1)
    b = (A @ x_true + 0.05 * g.standard_normal((A.shape[0], 1))).astype(np.float32)
    lam = 1e-3 * float((A.T @ b).max())
    problem = Problem(csr(A), torch.tensor(b), lam, grid_shape=(n, n, n),
                      voxel_index=torch.arange(n**3))
    error = {}
    for tv in (0.0, 1e-3):
        x = make_solver("tv", tv=tv, tol=1e-4, max_iters=5000).solve(problem).x.double().numpy()
        error[tv] = np.linalg.norm(x - x_true) / np.linalg.norm(x_true)
    assert error[1e-3] < 0.6 * error[0.0], error


def test_reweighted_round_reaches_the_dual_optimum_of_its_weighted_objective(tv_case):
    """reweight_rounds=1: the second solve minimises the objective with the Candes-Wakin-Boyd
    weights of the first solution, computed here by explicit loops, checked against SLSQP."""
    A, b, problem, lmax = tv_case
    options = {"tv": 0.05, "tol": 1e-6, "max_iters": 20_000}
    first = make_solver("tv", **options).solve(problem).x.double().numpy()
    res = make_solver("tv", **options, reweight_rounds=1, reweight_eps=0.2, reweight="both").solve(problem)
    assert (res.x >= 0).all() and {h["round"] for h in res.history} == {0, 1}
    D, owner = grouped_differences(GRID, HULL)
    sq = np.zeros_like(first)
    np.add.at(sq, owner, (D @ first) ** 2)
    eps = 0.2 * first.max(0)
    w_tv, w_l1 = eps / (np.sqrt(sq) + eps), eps / (first + eps)
    mu = 0.05 * lmax
    x = res.x.double().numpy()
    d = D @ x
    per_voxel = np.zeros_like(x)
    np.add.at(per_voxel, owner, d**2)
    ours = (0.5 * ((A.astype(np.float64) @ x - b) ** 2).sum() + (problem.l1 * w_l1 * x).sum()
            + (mu * w_tv * np.sqrt(per_voxel)).sum())
    ref = dual_reference(A, b, problem.l1 * w_l1, mu * w_tv, D, owner)
    assert abs(ours - ref) <= 1e-4 * ref
    assert res.objective == pytest.approx(ours, rel=1e-5)
    assert res.history[-1]["objective"] == pytest.approx(ours, rel=1e-5)
    assert res.history[-1]["rel_gap"] < 1e-4  # the gap of the weighted objective certifies it


def test_reweighted_tv_keeps_the_edges_plain_tv_rounds_off():
    """Denoising a 1D piecewise-constant signal (A = I on a 1 x 1 x n hull): plain TV lowers a
    narrow plateau by about 2 mu / width and leaves a bias everywhere; three reweighted rounds
    (edges weighted eps / (|jump| + eps)) recover the levels."""
    n = 60
    truth = np.zeros(n)
    truth[15:25], truth[25:45] = 1.0, 0.4
    g = np.random.default_rng(2)
    b = (truth + 0.02 * g.standard_normal(n)).clip(0).astype(np.float32)[:, None]
    problem = Problem(csr(np.eye(n, dtype=np.float32)), torch.tensor(b), 0.0, grid_shape=(1, 1, n),
                      voxel_index=torch.arange(n))
    error, plateau = {}, {}
    for rounds in (0, 3):
        x = make_solver("tv", tv=0.3, tol=1e-7, max_iters=20_000, reweight_rounds=rounds,
                        reweight_eps=0.05).solve(problem).x.double().numpy()[:, 0]
        error[rounds] = np.abs(x - truth).max()
        plateau[rounds] = x[15:25].mean()
    assert plateau[0] < 0.96 and abs(plateau[3] - 1.0) < 0.02, plateau  # TV's shrinkage, undone
    assert error[3] < 0.25 * error[0], error


def test_reweighting_refuses_bad_options():
    for bad, match in (({"reweight_rounds": -1}, "reweight_rounds"), ({"reweight_eps": 0.0}, "reweight_eps"),
                       ({"reweight": "edges"}, "reweight")):
        with pytest.raises(ValueError, match=match):
            make_solver("tv", **bad)


def test_resume_from_state_ends_where_an_uninterrupted_solve_ends(tv_case):
    _, _, problem, _ = tv_case
    assert_resumes_exactly("tv", {"tv": 0.05, "tol": 0.0, "max_iters": 200, "check_every": 10}, problem, at=70)


def test_an_interrupted_run_resumes_from_its_checkpoint_to_the_same_density(tmp_path, monkeypatch):
    cfg = tiny_cfg("grid.resolution=12", "solver=tv", "solver.tv=0.01", "solver.tol=0",
                   "solver.max_iters=30", "solver.check_every=5", "checkpoint.every=10")
    run, reference = tmp_path / "run", tmp_path / "reference"
    with pytest.raises(Interrupted, match="at iteration 15"):
        reconstruct(cfg, run, watch=interrupt_at(15))  # the run's handler: checkpoint, stop
    resumed = reconstruct(cfg, run, resume=True)
    straight = reconstruct(cfg, reference)
    # bit for bit on 2 threads; with 16 threads the CPU kernels' summation order moved the
    # objective by 3e-9 (relative), while resuming without the dual variable moves it by 1.6e-3
    assert resumed["solver"]["objective"] == pytest.approx(straight["solver"]["objective"], rel=1e-7)
    with np.load(run / "density.npz") as a, np.load(reference / "density.npz") as b:
        np.testing.assert_allclose(a["density"], b["density"], rtol=1e-5, atol=1e-7)


def test_bad_weights_and_missing_geometry_are_refused(tmp_path):
    with pytest.raises(ValueError, match="solver.tv must be >= 0"):
        make_solver("tv", tv=-0.1)
    with pytest.raises(ConfigError, match="solver.tv must be >= 0"):
        reconstruct(tiny_cfg("solver=tv", "solver.tv=-1"), tmp_path)
    A, b, lam = tiny_problem()
    with pytest.raises(ValueError, match="grid_shape"):
        make_solver("tv").solve(Problem(csr(A), torch.tensor(b), lam))


@pytest.mark.slow
@pytest.mark.e2e
def test_train_py_runs_solver_tv_and_logs_the_tv_term_and_weight(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, "train.py", *TINY, *FAST, "solver=tv", "solver.tv=0.05",
                           "solver.check_every=5", f"hydra.run.dir={run}"],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["solver"]["name"] == "tv" and metrics["solver"]["iterations"] == 10
    assert 10.0 < metrics["heldout"]["cam04"]["psnr"] < 80.0
    acc = ea.EventAccumulator(str(run), size_guidance={ea.SCALARS: 0})
    acc.Reload()
    tv = acc.Scalars("solve/tv")
    assert [e.step for e in tv] == [5, 10] and tv[-1].value > 0
    # the relative weight is an hparam, so a sweep over solver.tv shows in TensorBoard
    start = plugin_data_pb2.HParamsPluginData.FromString(
        acc.PluginTagToContent("hparams")["_hparams_/session_start_info"]).session_start_info
    assert start.hparams["tv"].number_value == pytest.approx(0.05)
