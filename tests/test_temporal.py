"""The joint frame solve against independent references: per-frame ``tv`` solves when the
coupling is off, a closed form for the squared coupling, SLSQP for the L1 couplings."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from flamerecon.operators import CsrOperator
from flamerecon.solvers import Problem, make_solver
from flamerecon.solvers.temporal import (
    FrameProblem,
    JointOptions,
    coupling_pairs,
    estimate_shift,
    solve_joint,
)


class Dense:
    """A dense matrix as a LinearOperator."""

    def __init__(self, A: torch.Tensor) -> None:
        self.A, self.shape = A, tuple(A.shape)

    def forward(self, x):
        return self.A @ x

    def adjoint(self, y):
        return self.A.T @ y


def frames_on_line(hulls: list[list[int]], n: int = 8, rows: int = 14, l1: float = 0.0,
                   tv: float = 0.0, seed: int = 0) -> list[FrameProblem]:
    """Frames on a (1, 1, n) grid, random nonnegative operators on the given hull cells."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for hull in hulls:
        A = torch.rand(rows, len(hull), generator=g, dtype=torch.float64)
        truth = torch.rand(len(hull), 1, generator=g, dtype=torch.float64) + 0.2
        b = A @ truth + 0.05 * torch.randn(rows, 1, generator=g, dtype=torch.float64)
        out.append(FrameProblem(Dense(A), b, l1, tv, (1, 1, n), torch.tensor(hull)))
    return out


HULLS = [[0, 1, 2, 3, 4, 5], [1, 2, 3, 4, 5, 6], [0, 2, 3, 4, 5, 7]]


def test_coupling_pairs_are_the_hull_intersections():
    pairs = coupling_pairs([torch.tensor(h) for h in HULLS])
    for (ia, ib), a, b in zip(pairs, HULLS[:-1], HULLS[1:]):
        common = sorted(set(a) & set(b))
        assert [a[i] for i in ia.tolist()] == common
        assert [b[i] for i in ib.tolist()] == common


def test_uncoupled_frames_match_the_single_frame_tv_solver():
    g = torch.Generator().manual_seed(3)
    shape = (2, 3, 4)
    frames, singles = [], []
    for hull in ([0, 1, 2, 5, 6, 9, 10, 13, 14, 17, 21], [1, 2, 3, 5, 6, 7, 9, 13, 17, 18, 22, 23]):
        idx = torch.tensor(hull)
        A = torch.rand(20, len(hull), generator=g, dtype=torch.float64)
        b = A @ (torch.rand(len(hull), 2, generator=g, dtype=torch.float64) + 0.1)
        frames.append(FrameProblem(Dense(A), b, 0.3, 0.2, shape, idx))
        tv_rel = 0.2 / float((A.T @ b).max())  # the tv solver's weight is relative to max(A^T b)
        solver = make_solver("tv", tv=tv_rel, max_iters=1500, tol=1e-12, check_every=50)
        singles.append(solver.solve(Problem(Dense(A), b, 0.3, grid_shape=shape, voxel_index=idx)).x)
    joint = solve_joint(frames, JointOptions(max_iters=1500, tol=1e-12, check_every=50))
    for x, ref in zip(joint.xs, singles):
        torch.testing.assert_close(x, ref, atol=1e-6, rtol=1e-5)


def test_squared_coupling_matches_the_closed_form():
    """Without L1/TV and with every x > 0, the optimum solves (blockdiag(A^T A) + w2 Lap) x = A^T b."""
    frames = frames_on_line(HULLS)
    w2 = 2.0
    sizes = [len(h) for h in HULLS]
    offsets = np.cumsum([0, *sizes])
    H = np.zeros((offsets[-1], offsets[-1]))
    rhs = np.zeros(offsets[-1])
    for t, f in enumerate(frames):
        A = f.A.A.numpy()
        sl = slice(offsets[t], offsets[t + 1])
        H[sl, sl] += A.T @ A
        rhs[sl] = A.T @ f.b.numpy()[:, 0]
    for t in range(len(HULLS) - 1):  # independent of coupling_pairs: shared cells by name
        for cell in set(HULLS[t]) & set(HULLS[t + 1]):
            i, j = offsets[t] + HULLS[t].index(cell), offsets[t + 1] + HULLS[t + 1].index(cell)
            H[i, i] += w2
            H[j, j] += w2
            H[i, j] -= w2
            H[j, i] -= w2
    ref = np.linalg.solve(H, rhs)
    assert (ref > 0).all()  # the nonnegativity constraint is inactive: the closed form holds
    joint = solve_joint(frames, JointOptions(l2=w2, max_iters=50000, tol=1e-13, check_every=100))
    got = torch.cat(joint.xs)[:, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=1e-6, rtol=1e-5)
    uncoupled = np.concatenate([np.linalg.lstsq(f.A.A.numpy(), f.b.numpy()[:, 0], rcond=None)[0]
                                for f in frames])
    assert np.abs(got - uncoupled).max() > 1e-3  # the coupling did change the answer


def slsqp_reference(frames: list[FrameProblem], w2: float, w1: float) -> np.ndarray:
    """min of the joint objective on a (1, 1, n) grid by SLSQP, |.| terms as slack variables."""
    sizes = [int(f.voxel_index.numel()) for f in frames]
    offsets = np.cumsum([0, *sizes])
    hulls = [f.voxel_index.tolist() for f in frames]
    spatial = [(offsets[t] + h.index(c), offsets[t] + h.index(c + 1), frames[t].tv)
               for t, h in enumerate(hulls) for c in h if c + 1 in h]
    temporal = [(offsets[t] + hulls[t].index(c), offsets[t + 1] + hulls[t + 1].index(c))
                for t in range(len(hulls) - 1) for c in set(hulls[t]) & set(hulls[t + 1])]
    terms = [(i, j, w) for i, j, w in spatial] + [(i, j, w1) for i, j in temporal]
    n, k = offsets[-1], len(terms)
    As = [f.A.A.numpy() for f in frames]
    bs = [f.b.numpy()[:, 0] for f in frames]
    l1 = np.concatenate([np.full(m, f.l1) for f, m in zip(frames, sizes)])
    wt = np.array([w for _, _, w in terms])
    ii, jj = np.array([t[0] for t in terms]), np.array([t[1] for t in terms])
    ti, tj = np.array([t[0] for t in temporal]), np.array([t[1] for t in temporal])

    def fun(v):
        x, s = v[:n], v[n:]
        r = [A @ x[offsets[t]:offsets[t + 1]] - b for t, (A, b) in enumerate(zip(As, bs))]
        d = x[tj] - x[ti]
        val = sum(0.5 * ri @ ri for ri in r) + l1 @ x + wt @ s + 0.5 * w2 * d @ d
        gx = l1.copy()
        for t, (A, ri) in enumerate(zip(As, r)):
            gx[offsets[t]:offsets[t + 1]] += A.T @ ri
        np.add.at(gx, tj, w2 * d)
        np.add.at(gx, ti, -w2 * d)
        return val, np.concatenate([gx, wt])

    cons = {"type": "ineq",
            "fun": lambda v: np.concatenate([v[n:] - (v[jj] - v[ii]), v[n:] + (v[jj] - v[ii])])}
    v0 = np.concatenate([np.full(n, 0.5), np.ones(k)])
    res = minimize(fun, v0, jac=True, method="SLSQP", constraints=[cons],
                   bounds=[(0, None)] * (n + k), options={"maxiter": 2000, "ftol": 1e-12})
    assert res.success, res.message
    return res.x[:n]


@pytest.mark.parametrize("w2, w1", [(0.0, 0.8), (1.5, 0.3)])
def test_l1_couplings_match_slsqp(w2, w1):
    frames = frames_on_line(HULLS, l1=0.4, tv=0.5, seed=1)
    ref = slsqp_reference(frames, w2, w1)
    joint = solve_joint(frames, JointOptions(l2=w2, tv=w1, max_iters=100000, tol=1e-13, check_every=100))
    got = torch.cat(joint.xs)[:, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=2e-4)


def test_joint_solve_runs_on_sparse_operators_in_float32():
    """The pipeline's CSR operators (float32) pass through the same path."""
    g = torch.Generator().manual_seed(0)
    frames = []
    for hull in HULLS:
        dense = torch.rand(10, len(hull), generator=g)
        rows, cols = dense.nonzero(as_tuple=True)
        A = CsrOperator.from_coo(rows, cols, dense[rows, cols], tuple(dense.shape))
        frames.append(FrameProblem(A, dense @ torch.ones(len(hull), 1), 0.0, 0.0, (1, 1, 8),
                                   torch.tensor(hull)))
    joint = solve_joint(frames, JointOptions(l2=0.5, tv=0.1, max_iters=200, tol=1e-9))
    assert all(x.dtype == torch.float32 and (x >= 0).all() for x in joint.xs)
    assert joint.history[-1]["objective"] < joint.history[0]["objective"]


def test_estimate_shift_recovers_a_known_motion():
    g = torch.Generator().manual_seed(5)
    a = torch.zeros(12, 10, 14)
    a[3:7, 2:6, 4:9] = torch.rand(4, 4, 5, generator=g) + 0.5
    b = torch.roll(a, shifts=(2, -1, 1), dims=(0, 1, 2))  # dz=2, dy=-1, dx=1
    assert estimate_shift(a, b, 3) == (1, -1, 2)
    assert estimate_shift(a, a, 3) == (0, 0, 0)


def test_shifted_pairs_follow_the_motion():
    shape = (3, 4, 5)  # nz, ny, nx
    hull_a = torch.arange(0, 60, 2)
    hull_b = torch.arange(0, 60, 3)
    (ia, ib), = coupling_pairs([hull_a, hull_b], shape, [(1, 0, 1)])
    expected = []
    for pa, v in enumerate(hull_a.tolist()):
        k, i = v // 20, v % 5
        if i + 1 < 5 and k + 1 < 3 and (w := v + 20 + 1) in hull_b.tolist():
            expected.append((pa, hull_b.tolist().index(w)))
    assert list(zip(ia.tolist(), ib.tolist())) == expected and expected


@pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device")
def test_joint_solve_on_cuda_matches_cpu():
    frames = frames_on_line(HULLS, l1=0.4, tv=0.5, seed=1)
    opts = JointOptions(l2=1.5, tv=0.3, max_iters=500, tol=0.0)
    cpu = solve_joint(frames, opts)
    cuda = [FrameProblem(Dense(f.A.A.cuda()), f.b.cuda(), f.l1, f.tv, f.grid_shape,
                         f.voxel_index.cuda()) for f in frames]
    gpu = solve_joint(cuda, opts)
    for a, b in zip(cpu.xs, gpu.xs):
        torch.testing.assert_close(b.cpu(), a, atol=1e-8, rtol=1e-6)
    vol = torch.rand(6, 7, 8, dtype=torch.float64)
    assert estimate_shift(vol.cuda(), torch.roll(vol, 1, 0).cuda(), 2) == estimate_shift(
        vol, torch.roll(vol, 1, 0), 2)
