"""Solver speed on the paper-scale problem: ours against scikit-learn, skglm and celer.

The problem: the built-in synthetic flame, 8 views of 320x240, silhouette rays x visual-hull
voxels on an N^3 grid, trilinear assembled operator A (float32 CSR), data P (N_rays, 3), and
lambda = l1_rel * max(A^T P); per colour column c, F_c(x) = 0.5||A x - P_c||^2 + lambda sum(x),
x >= 0, and F = sum_c F_c.

f* comes from a float64 reference solve (``pqn`` in float32, then in float64, then an
active-set conjugate-gradient polish per column) whose duality gap certifies it: f* lies in
[dual bound, f_ref], and the report says how tight. It is cached beside the problem dump (``--dump``, default a user cache folder) under
a hash of (A, P, lambda), so it is computed once per problem. Every method then runs on the
identical problem; each iterate's objective is recomputed in float64 by :func:`objectives`
(the one function, its time not counted) and the time to a relative gap (F - f_ref) / f_ref of
1e-4 and 1e-6 is reported. Ours run on all columns at once (float32, after a warm-up solve),
on 1 thread, the peers' cores, and on ``--threads`` (default: the free cores, as ``threads:
null``); our lead is printed for both, with the load average. The peers (single-threaded, ``pip
install -e ".[bench]"``, a missing one skipped with a note) run per column in float64 with their own iteration
or tolerance budget swept (cold runs, doubling) until the gap or the time budget is reached,
each after a JIT warm-up on a small slice. Also: the memory bandwidth, the time of one A x and
one A^T y against bytes(A) / bandwidth, and a fused A^T (A y - b) in one sweep (numba).
``--solvers`` takes any registered solver: ``mart``, ``sart`` and ``cgls`` ignore lambda, so
they are timed on the same problem and reported with the gap they reach (never 1e-4: their
fixed point is not the LASSO's), the cost of the algebraic baselines beside ours.

    PYTHONPATH=. python scripts/benchmark.py --grid 64 128 --threads 2
    PYTHONPATH=. python scripts/benchmark.py --grid 64 --solvers fista mart sart --peers
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import hashlib
import multiprocessing as mp
import os
import platform
import queue as queue_module
import sys
import time
import warnings
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np
import torch

from flamerecon.device import resolve_device, set_threads
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import visual_hull
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.operators.projector import assemble, camera_rays
from flamerecon.operators.sparse import CsrOperator
from flamerecon.outputs.atomic import atomic_path, make_folder, save_npz_atomic, write_json_atomic
from flamerecon.progress import Progress
from flamerecon.run.cli import output_file, output_folder, run_script, script_parser
from flamerecon.scenes import load_scene
from flamerecon.solvers import SOLVERS, Problem, lambda_max, make_solver

TARGETS = (1e-4, 1e-6)
OURS = ("fista", "newton_cg", "pqn", "ssnal")
ONE = " (1 thread)"  # suffix of ours on one thread, the cores the peers run on
PEERS = ("sklearn_lasso", "skglm_lasso", "celer_lasso", "sklearn_lassolars")
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "flamerecon" / "benchmark"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device, repeats: int = 5) -> float:
    """Median seconds of ``fn()`` after one warm-up call."""
    fn()
    sync(device)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def memory_bandwidth(device: torch.device, nbytes: int = 256 << 20) -> float:
    """Bytes per second of a large on-device copy (read + write counted)."""
    src = torch.ones(nbytes // 4, dtype=torch.float32, device=device)
    dst = torch.empty_like(src)
    return 2 * nbytes / timed(lambda: dst.copy_(src), device)


def build_problem(n: int, device: torch.device) -> dict:
    """Synthetic flame restricted to its hull on an n^3 grid: A, P (N, 3), grid, hull index."""
    scene = load_scene({"name": "synthetic"})
    masks = silhouettes(scene.images)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, (n, n, n))
    cams = scene.cameras
    hull = visual_hull(grid, cams, masks)
    voxel_index = hull.reshape(-1).nonzero()[:, 0]
    rays, pixel = camera_rays(cams, masks)
    start = time.perf_counter()
    A = assemble(grid, rays.to(device), voxel_index.to(device))
    sync(device)
    seconds = time.perf_counter() - start
    P = scene.images.permute(0, 2, 3, 1).reshape(-1, scene.images.shape[1])[pixel.cpu()]
    return {"A": A, "P": P.contiguous().to(device), "grid": grid, "voxel_index": voxel_index,
            "assembly_seconds": seconds}


def objectives(A64: torch.Tensor, P64: torch.Tensor, lam: float, x) -> np.ndarray:
    """F_c(x) (C,) in float64 for x (M, C) or (C, M) numpy/torch: THE objective every method's
    iterate is scored with (A64 a float64 CSR copy of A, P64 (N, C) float64)."""
    x = torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x).to(P64)
    x = x.reshape(A64.shape[1], -1) if x.shape[0] == A64.shape[1] else x.T
    r = A64 @ x - P64
    return (0.5 * (r * r).sum(0) + lam * x.abs().sum(0)).cpu().numpy()


class Tracer:
    """Records (solver seconds, total float64 objective) pairs; its own time is not counted."""

    def __init__(self, A64: torch.Tensor, P64: torch.Tensor, lam: float) -> None:
        self.A64, self.P64, self.lam = A64, P64, lam
        self.start = time.perf_counter()
        self.overhead = 0.0
        self.trace: list[tuple[float, float]] = []

    def record(self, x) -> None:
        t = time.perf_counter()
        self.trace.append((t - self.start - self.overhead,
                           float(objectives(self.A64, self.P64, self.lam, x).sum())))
        self.overhead += time.perf_counter() - t


def problem_key(A: CsrOperator, P: torch.Tensor, lam: float) -> str:
    """A hash of (A, P, lambda): the reference cache's key."""
    h = hashlib.sha1()
    for t in (A.A.crow_indices(), A.A.col_indices(), A.A.values(), P):
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(repr(float(lam)).encode())
    return h.hexdigest()


def dual_bound(A64, b: np.ndarray, lam: float, u: np.ndarray) -> float:
    """A lower bound on one column's optimum: the dual value of ``u`` scaled into
    {A^T u <= lambda}."""
    worst = (A64.T @ u).max()
    s = min(1.0, lam / worst) if worst > 0 else 1.0
    return float(b @ (s * u) - 0.5 * (s * u) @ (s * u))


def column_bounds(A64, b: np.ndarray, lam: float, x: np.ndarray) -> tuple[float, float]:
    """(primal value, dual lower bound) of one column at a feasible ``x`` (dual point: the
    residual b - A x)."""
    r = A64 @ x - b
    return float(0.5 * r @ r + lam * x.sum()), dual_bound(A64, b, lam, -r)


def polish_column(A64, b: np.ndarray, lam: float, x: np.ndarray, rounds: int = 8,
                  cg_iters: int = 3000) -> tuple[np.ndarray, float, float]:
    """Active-set polish of one column (Lawson-Hanson style): CG on the normal equations of the
    support S, then S loses the voxels the solve made negative and gains those whose gradient
    descends, until neither happens; returns (x, primal, dual lower bound).

    The dual point is u = b - A_S z of the support solution z, scaled into {A^T u <= lambda}:
    tight once S is the optimum's support.
    """
    A_csc = A64.tocsc()

    def primal(v):
        r = A64 @ v - b
        return 0.5 * r @ r + lam * v.sum()

    best_x, (best_p, best_d) = x, column_bounds(A64, b, lam, x)
    S = np.nonzero(x > 0)[0]
    for _ in range(rounds):
        AS = A_csc[:, S].tocsr()
        AST = AS.T.tocsr()
        z = x[S].copy()
        res = AST @ b - lam - AST @ (AS @ z)
        p, rr = res.copy(), res @ res
        stop = (1e-10 * np.linalg.norm(AST @ b)) ** 2
        for _ in range(cg_iters):
            if rr <= stop:
                break
            q = AST @ (AS @ p)
            alpha = rr / (p @ q)
            z += alpha * p
            res -= alpha * q
            rr, rr_old = res @ res, rr
            p = res + (rr / rr_old) * p
        best_d = max(best_d, dual_bound(A64, b, lam, b - AS @ z))
        x = np.zeros_like(x)
        x[S] = np.maximum(z, 0)
        if primal(x) < best_p:
            best_x, best_p = x, primal(x)
        g = A64.T @ (A64 @ x - b) + lam
        keep = S[z > 0]
        enter = np.setdiff1d(np.nonzero(g < 0)[0], S)
        if best_p - best_d <= 1e-12 * best_p or (len(keep) == len(S) and len(enter) == 0):
            break
        S = np.union1d(keep, enter)
    return best_x, float(best_p), float(best_d)


def solve_progress(what: str, iters: int):
    """A solver callback that logs the iterations done of at most ``iters`` (every 10 s; the
    remaining time is an upper bound: the solve stops at its tolerance)."""
    progress = Progress(what, iters, unit="iteration", every=10.0)
    return lambda it, x, info: progress.update(it, f"relative gap {info['rel_gap']:.1e}" if "rel_gap" in info else "")


def reference(A: CsrOperator, P: torch.Tensor, lam: float, cache: Path, iters: int) -> dict:
    """The certified float64 optimum of every column, from ``cache/reference.npz`` when its
    key matches (A, P, lambda), else solved (``pqn`` in float32, then from there in float64
    to a 1e-9 duality gap or ``iters`` iterations, then :func:`polish_column`) and written
    there. Returns x (M, C), f (C,) primal and lower (C,) dual bounds, seconds."""
    key = problem_key(A, P, lam)
    path = cache / "reference.npz"
    if path.exists():
        got = np.load(path)
        if str(got["key"]) == key:
            return {"x": got["x"], "f": got["f"], "lower": got["lower"],
                    "seconds": float(got["seconds"]), "cached": True}
    start = time.perf_counter()
    # float32 gets the objective to ~1e-6 (its duality gap may stay above: at most 1000 iterations)
    x32 = make_solver("pqn", tol=1e-6, max_iters=min(iters, 1000)).solve(
        Problem(A, P, lam), callback=solve_progress("reference solve, float32", min(iters, 1000))).x
    A64op = CsrOperator(A.A.cpu().double(), A.AT.cpu().double())
    P64 = P.cpu().double()
    solver = make_solver("pqn", tol=1e-9, max_iters=iters, check_every=10)
    found = solver.solve(Problem(A64op, P64, lam), x0=x32.cpu().double(),
                         callback=solve_progress("reference solve, float64", iters))
    x = found.x.numpy()
    print(f"  reference: pqn in float64, {found.iterations} iterations, relative gap "
          f"{found.history[-1]['rel_gap'] if found.history else float('nan'):.1e}, "
          f"{time.perf_counter() - start:.0f} s", flush=True)
    A64 = A.to_scipy().astype(np.float64)
    f, lower = np.zeros(x.shape[1]), np.zeros(x.shape[1])
    for c in range(x.shape[1]):
        b = P64[:, c].numpy()
        f[c], lower[c] = column_bounds(A64, b, lam, x[:, c])
        if f[c] - lower[c] > 1e-9 * f[c]:  # the active-set polish only where pqn stopped short
            x[:, c], f[c], lower[c] = polish_column(A64, b, lam, x[:, c].copy())
    seconds = time.perf_counter() - start
    make_folder(cache)
    save_npz_atomic(path, key=key, x=x, f=f, lower=lower, seconds=seconds)
    return {"x": x, "f": f, "lower": lower, "seconds": seconds, "cached": False}


def run_ours(name: str, problem: Problem, tracer: Tracer, budget: float) -> dict:
    """One of our solvers on all columns at once, traced every 10 iterations, after a short
    warm-up solve (first-call costs excluded, as for the peers' JIT)."""
    make_solver(name, tol=0.0, max_iters=3, check_every=1).solve(problem)
    solver = make_solver(name, tol=1e-12, max_iters=10**7, max_seconds=budget,
                         check_every=10 if name in ("fista", "pqn") else 1)
    tracer.start = time.perf_counter()
    result = solver.solve(problem, callback=lambda it, x, info: tracer.record(x))
    return {"iterations": result.iterations, "x": result.x.cpu().numpy()}


def peer_fit(label: str, level: float, alpha: float):
    """A fitted-per-column peer estimator at one budget level: scikit-learn's epochs (tol 0),
    skglm's and celer's tolerance (their working-set solvers stop on it)."""
    common = {"alpha": alpha, "positive": True, "fit_intercept": False}
    if label == "sklearn_lasso":
        from sklearn.linear_model import Lasso

        return Lasso(**common, tol=0.0, max_iter=int(level))
    if label == "skglm_lasso":
        from skglm import Lasso

        return Lasso(**common, tol=level, max_iter=1000, max_epochs=100_000)
    from celer import Lasso

    return Lasso(**common, tol=level, max_iter=1000, max_epochs=100_000)


def peer_levels(label: str):
    """The swept budget: epochs doubling from 10, or tolerances / 10 from 1e-3."""
    if label == "sklearn_lasso":
        return [10 * 2**k for k in range(20)]
    return [10.0 ** -k for k in range(3, 15)]


def _peer_child(label, level, A_csc, P64, alpha, out) -> None:
    coefs, seconds = [], 0.0
    for c in range(P64.shape[1]):
        model = peer_fit(label, level, alpha)
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(A_csc, P64[:, c])
        seconds += time.perf_counter() - start
        coefs.append(np.asarray(model.coef_, dtype=np.float64).ravel())
    out.put({"seconds": seconds, "x": np.stack(coefs, 1)})


def peer_installed(label: str) -> str | None:
    """None if the peer's package imports, else why it is skipped."""
    module = {"sklearn_lasso": "sklearn", "skglm_lasso": "skglm", "celer_lasso": "celer",
              "sklearn_lassolars": "sklearn"}[label]
    try:
        __import__(module)
    except ImportError:
        return f"{module} not installed (pip install -e \".[bench]\")"
    return None


def sweep_peer(label: str, A_csc, P64: np.ndarray, lam: float, f_ref: float, A64_t, P64_t,
               budget: float) -> dict:
    """Cold fits of every column at growing budgets (each in a forked child, abandoned past
    ``budget`` s) until the 1e-6 gap or the time budget; trace of (seconds, objective)."""
    alpha = lam / A_csc.shape[0]  # the peers minimise (1/2N)||Aw - p||^2 + alpha ||w||_1
    _peer_child(label, peer_levels(label)[0], A_csc[:200].tocsc()[:, :300], P64[:200], alpha,
                queue_module.Queue())  # JIT warm-up (skglm's numba) before any timing
    ctx = mp.get_context("fork")
    trace, levels = [], []
    for level in peer_levels(label):
        out = ctx.Queue()
        child = ctx.Process(target=_peer_child, args=(label, level, A_csc, P64, alpha, out),
                            daemon=True)
        child.start()
        try:
            got = out.get(timeout=2 * budget)
        except queue_module.Empty:
            got = None
        finally:
            child.terminate()
            child.join()
        if got is None:
            break
        f = float(objectives(A64_t, P64_t, lam, got["x"]).sum())
        trace.append((got["seconds"], f))
        levels.append(level)
        if (f - f_ref) / f_ref <= TARGETS[-1] or got["seconds"] > budget:
            break
    return {"trace": trace, "levels": levels}


def lars_fits(N: int, M: int) -> tuple[bool, str]:
    """LassoLars needs X dense (8 N M bytes) and its Gram (8 M^2); compare with free memory."""
    need = 8 * N * M + 8 * M * M
    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        free = 0
    if need < 0.5 * free:
        return True, ""
    return False, f"needs {need / 1e9:.1f} GB dense (X and Gram), {free / 1e9:.1f} GB free"


def _lassolars_child(A64, P64: np.ndarray, lam: float, queue) -> None:
    from sklearn.linear_model import LassoLars

    X = A64.toarray()
    start = time.perf_counter()
    model = LassoLars(alpha=lam / X.shape[0], positive=True, fit_intercept=False,
                      max_iter=10 * X.shape[1]).fit(X, P64)
    queue.put({"seconds": time.perf_counter() - start, "iterations": int(np.max(model.n_iter_)),
               "x": np.asarray(model.coef_).T})


def run_lassolars(A64, P64: np.ndarray, lam: float, budget: float) -> dict | None:
    """LassoLars (dense X) in a forked process, abandoned past ``budget`` seconds (it has no
    iteration callback or time limit of its own); None if it did not finish."""
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_lassolars_child, args=(A64, P64, lam, queue), daemon=True)
    child.start()
    try:
        densify = 10 * 8 * A64.shape[0] * A64.shape[1] / 1e9  # allow 10 s per GB of dense X
        return queue.get(timeout=budget + densify)
    except queue_module.Empty:  # out of budget
        return None
    finally:
        child.terminate()
        child.join()


def fused_seconds(A: CsrOperator, y: torch.Tensor, b: torch.Tensor) -> tuple[float, float] | None:
    """Median seconds of A^T (A y - b) as one sweep over the rows of A (numba: each row's
    residual, then its scatter into a per-thread copy of the result, summed), and its largest
    difference from the two-product result relative to that result's largest entry; None
    without numba."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(parallel=True, cache=False)
    def kernel(crow, col, val, y, b, parts):
        n, threads, C = crow.shape[0] - 1, parts.shape[0], y.shape[1]
        chunk = (n + threads - 1) // threads
        for t in numba.prange(threads):
            out = parts[t]
            out[:] = 0
            r = np.empty(C, dtype=y.dtype)
            for i in range(t * chunk, min(n, (t + 1) * chunk)):
                for c in range(C):
                    r[c] = -b[i, c]
                for k in range(crow[i], crow[i + 1]):
                    for c in range(C):
                        r[c] += val[k] * y[col[k], c]
                for k in range(crow[i], crow[i + 1]):
                    for c in range(C):
                        out[col[k], c] += val[k] * r[c]
        return parts.sum(0)

    crow, col = A.A.crow_indices().numpy(), A.A.col_indices().numpy()
    val, yn, bn = A.A.values().numpy(), y.numpy(), b.numpy()
    parts = np.empty((numba.get_num_threads(), A.shape[1], y.shape[1]), dtype=yn.dtype)
    seconds = timed(lambda: kernel(crow, col, val, yn, bn, parts), torch.device("cpu"))
    want = A.adjoint(A.forward(y) - b).numpy()
    err = float(np.abs(kernel(crow, col, val, yn, bn, parts) - want).max() / np.abs(want).max())
    return seconds, err


def write_json(path: Path, data: dict) -> None:
    make_folder(path.parent)
    write_json_atomic(path, data)


def dump(folder: Path, A, P: np.ndarray, lam: float, x: np.ndarray) -> None:
    """A.npz (scipy CSR) and problem.npz (P, lam, x), each written whole or not at all."""
    import scipy.sparse as sp

    make_folder(folder)
    for name, save in (("A.npz", lambda f: sp.save_npz(f, A)),
                       ("problem.npz", lambda f: np.savez(f, P=P, lam=lam, x=x))):
        with atomic_path(folder / name) as tmp, open(tmp, "wb") as f:
            save(f)


def seconds_to(trace: list[tuple[float, float]], f_ref: float, target: float) -> float | None:
    """The least time in ``trace`` at which (F - f_ref) / f_ref <= target, or None."""
    hits = [seconds for seconds, f in trace if (f - f_ref) / f_ref <= target]
    return min(hits) if hits else None


def swept_bracket(trace: list[tuple[float, float]], f_ref: float, target: float) -> list[float] | None:
    """For a peer's sweep of cold runs (growing budgets): [seconds of the last run still above
    ``target``, seconds of the first at or below it]: its time to the target lies in between
    (the first run's own time stands for both ends when it already gets there). None if none does."""
    for k, (seconds, f) in enumerate(trace):
        if (f - f_ref) / f_ref <= target:
            return [trace[k - 1][0] if k else seconds, seconds]
    return None


def lead(methods: dict, ours: tuple[str, ...] = OURS) -> dict | None:
    """Our fastest method of ``ours`` to 1e-4 against the fastest peer's bracket: the ratio at
    both ends."""
    peers = [(m["bracket_1e-4"], name) for name, m in methods.items()
             if name.removesuffix(ONE) not in OURS and m["bracket_1e-4"]]  # ours on any cores are not peers
    found = [(m["seconds_to_1e-4"], name) for name, m in methods.items()
             if name in ours and m["seconds_to_1e-4"] is not None]
    if not found or not peers:
        return None
    (t, name), (bracket, peer) = min(found), min(peers, key=lambda p: p[0][1])
    return {"ours": name, "seconds": t, "peer": peer, "peer_bracket": bracket,
            "ratio": [bracket[0] / t, bracket[1] / t]}


def benchmark_grid(n: int, args, device: torch.device) -> dict:
    t0 = time.perf_counter()
    built = build_problem(n, device)
    A, P = built["A"], built["P"]
    N, M = A.shape
    lam = args.l1_rel * lambda_max(A, P)
    print(f"grid {n}^3: {N} rays x {M} hull voxels, nnz {A.nnz}, {A.nbytes() / 1e6:.0f} MB per "
          f"copy, assembled in {built['assembly_seconds']:.1f} s (setup {time.perf_counter() - t0:.0f} s)"
          f"; load average {os.getloadavg()[0]:.2f}", flush=True)

    bw = memory_bandwidth(device)
    x1 = torch.rand(M, P.shape[1], device=device)
    y1 = torch.rand(N, P.shape[1], device=device)
    t_ax, t_aty = timed(lambda: A.forward(x1), device), timed(lambda: A.adjoint(y1), device)
    t_pair = timed(lambda: A.adjoint(A.forward(x1) - P), device)
    bound = A.nbytes() / bw
    fused = fused_seconds(A, x1, P) if device.type == "cpu" else None
    print(f"bandwidth {bw / 1e9:.1f} GB/s; A x {t_ax * 1e3:.1f} ms, A^T y {t_aty * 1e3:.1f} ms, "
          f"bound {bound * 1e3:.1f} ms each; pair at {(t_ax + t_aty) / (2 * bound):.1f}x the bound; "
          f"A^T(A y - b) {t_pair * 1e3:.1f} ms as two products"
          + ("" if fused is None else f", {fused[0] * 1e3:.1f} ms fused (numba, one sweep, "
             f"{fused[0] / bound:.1f}x one read of A; max rel. difference {fused[1]:.1e})"),
          flush=True)

    folder = Path(args.dump) / f"grid{n}"
    ref = reference(A, P, lam, folder, args.reference_iters)
    f_ref, lower = float(ref["f"].sum()), float(ref["lower"].sum())
    certified = (f_ref - lower) / f_ref
    print(f"reference f* = {f_ref:.10g} (float64, {'cached' if ref['cached'] else 'solved'} in "
          f"{ref['seconds']:.0f} s), certified by its duality gap to {certified:.1e} relative",
          flush=True)
    if not (folder / "A.npz").exists():
        dump(folder, A.to_scipy(), P.cpu().numpy(), lam, ref["x"])

    A64_device, P64_device = A.A.to(torch.float64), P.double()  # for objectives()
    problem = Problem(A, P, lam, grid_shape=built["grid"].shape, voxel_index=built["voxel_index"])
    runs: dict[str, dict] = {}
    traces: dict[str, list] = {}
    threads = torch.get_num_threads()
    counts = [(threads, ""), (1, ONE)] if threads > 1 and device.type == "cpu" else [(threads, "")]
    for count, suffix in counts:
        torch.set_num_threads(count)
        for name in args.solvers:
            tracer = Tracer(A64_device, P64_device, lam)
            key = name + suffix
            runs[key] = run_ours(name, problem, tracer, args.budget)
            traces[key] = tracer.trace
            print(f"  {key}: {runs[key]['iterations']} iterations, {tracer.trace[-1][0]:.1f} s, rel. gap "
                  f"{(tracer.trace[-1][1] - f_ref) / f_ref:.1e}; load average {os.getloadavg()[0]:.2f}", flush=True)
    torch.set_num_threads(threads)
    skipped = {}
    coordinate = [p for p in args.peers if p != "sklearn_lassolars"]
    A64 = P64 = A_csc = None
    for label in args.peers:
        why = peer_installed(label)
        if why is not None:
            skipped[label] = why
            print(f"  {label}: skipped ({why})")
            continue
        if A64 is None:  # the peers' input (CPU, float64), built only when a peer runs
            A64, P64 = A.to_scipy().astype(np.float64), P.cpu().double().numpy()
            A_csc = A64.tocsc() if coordinate else None
        if label == "sklearn_lassolars":
            fits, why = lars_fits(N, M)
            got = run_lassolars(A64, P64, lam, args.budget) if fits else None
            if got is None:
                skipped[label] = why or f"did not finish within the {args.budget:g} s budget"
                print(f"  {label}: skipped ({skipped[label]})")
                continue
            traces[label] = [(got["seconds"],
                              float(objectives(A64_device, P64_device, lam, got["x"]).sum()))]
            runs[label] = {"iterations": got["iterations"], "levels": []}
        else:
            got = sweep_peer(label, A_csc, P64, lam, f_ref, A64_device, P64_device, args.budget)
            traces[label] = got["trace"]
            runs[label] = {"iterations": len(got["levels"]), "levels": got["levels"]}
            if not got["trace"]:
                skipped[label] = f"its first level did not finish within {2 * args.budget:g} s"
                del traces[label]
                continue
        print(f"  {label}: levels {runs[label]['levels']}, last {traces[label][-1][0]:.1f} s, "
              f"rel. gap {(traces[label][-1][1] - f_ref) / f_ref:.1e}; load average "
              f"{os.getloadavg()[0]:.2f}", flush=True)

    methods = {}
    for name, trace in traces.items():
        methods[name] = {
            **{f"seconds_to_{t:.0e}".replace("e-0", "e-"): seconds_to(trace, f_ref, t)
               for t in TARGETS},
            "iterations": runs[name]["iterations"],
            "levels": runs[name].get("levels"),
            "bracket_1e-4": swept_bracket(trace, f_ref, TARGETS[0]) if runs[name].get("levels") else None,
            "objective": trace[-1][1],
            "best_rel_gap": min((f - f_ref) / f_ref for _, f in trace),
            "seconds": trace[-1][0],
            "trace": [[round(s, 4), f] for s, f in trace],
        }
    return {
        "grid": [n, n, n], "rays": N, "voxels": M, "nnz": A.nnz, "l1_rel": args.l1_rel,
        "lambda": lam, "reference_objective": f_ref, "reference_lower_bound": lower,
        "reference_certified_rel_gap": certified, "reference_seconds": ref["seconds"],
        "budget_seconds": args.budget, "assembly_seconds": built["assembly_seconds"],
        "load_average": os.getloadavg(), "bandwidth_GBps": bw / 1e9, "seconds_Ax": t_ax,
        "seconds_ATy": t_aty, "seconds_normal_pair": t_pair,
        "seconds_normal_fused": None if fused is None else fused[0],
        "seconds_bound_each": bound, "methods": methods, "skipped": skipped, "threads": threads,
        # the same cores: ours on 1 thread (on all when that is 1, or on a GPU) against the peers
        "lead_1e-4": lead(methods, tuple(n + ONE for n in args.solvers if n + ONE in methods) or OURS),
        "lead_1e-4_threads": lead(methods, OURS),
    }


def print_table(report: dict) -> None:
    def fmt(v):
        return "  > budget" if v is None else f"{v:10.2f}"

    print(f"\n{report['grid'][0]}^3, lambda = {report['l1_rel']:g} max(A^T P), f* = "
          f"{report['reference_objective']:.10g} (certified to "
          f"{report['reference_certified_rel_gap']:.1e}), load average "
          f"{report['load_average'][0]:.2f}")
    print(f"{'method':<22}{'s to 1e-4':>10}{'s to 1e-6':>10}{'best gap':>10}{'iters':>8}   "
          f"(a peer's 1e-4 time lies after its last run above 1e-4)")
    for name, m in report["methods"].items():
        bracket = m.get("bracket_1e-4")
        after = f"   (after {bracket[0]:.2f})" if bracket and bracket[0] < bracket[1] else ""
        print(f"{name:<22}{fmt(m['seconds_to_1e-4'])}{fmt(m['seconds_to_1e-6'])}"
              f"{m['best_rel_gap']:>10.1e}{m['iterations']:>8}{after}")
    for name, why in report["skipped"].items():
        print(f"{name:<22}skipped: {why}")
    same = report.get("lead_1e-4")
    for where, won in (("on the peers' cores", same),
                       (f"ours on {report.get('threads')} threads", report.get("lead_1e-4_threads"))):
        if won and (where.startswith("on") or won != same):
            lo, hi = won["peer_bracket"]
            print(f"to 1e-4 {where}: {won['ours']} {won['seconds']:.2f} s, the fastest peer {won['peer']} between "
                  f"{lo:.2f} and {hi:.2f} s: {won['ratio'][0]:.1f}x to {won['ratio'][1]:.1f}x sooner "
                  f"(load average {report['load_average'][0]:.2f})")


def check_args(args) -> None:
    """Refuse a bad command line before any work (building the problem takes seconds)."""
    from flamerecon.errors import ConfigError

    bad = [n for n in args.grid if n < 2]
    if bad:
        raise ConfigError(f"--grid: {bad[0]} is not a grid size; give N >= 2 (cells per side of N^3)")
    if not args.budget > 0:
        raise ConfigError(f"--budget: got {args.budget}; give the seconds per method, > 0")
    if not args.l1_rel >= 0:
        raise ConfigError(f"--l1-rel: got {args.l1_rel}; give lambda / max(A^T P) >= 0")
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads: got {args.threads}; give a positive number of threads")
    unknown = [s for s in args.solvers if s not in SOLVERS]
    if unknown:
        raise ConfigError(f"--solvers: unknown solver {unknown[0]!r}; choose from {sorted(SOLVERS)}")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--grid", type=int, nargs="+", default=[64], help="grid sizes N (N^3)")
    parser.add_argument("--l1-rel", type=float, default=1e-3, help="lambda / max(A^T P)")
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per method")
    parser.add_argument("--solvers", nargs="*", default=list(OURS),
                        help="ours, e.g. fista lbfgsb; the baselines mart sart cgls ignore lambda")
    parser.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS,
                        help="peers to time (default: all; installed ones run)")
    parser.add_argument("--reference-iters", type=int, default=4000,
                        help="at most this many float64 pqn iterations before the reference's polish")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads of ours' second run (default: the free cores); ours also run on 1")
    parser.add_argument("--out", type=output_file, default="benchmark.json", help="the report (JSON)")
    parser.add_argument("--dump", type=output_folder, default=str(CACHE),
                        help="folder for grid<N>/ A.npz, problem.npz, reference.npz (the cache)")
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args) -> None:
    check_args(args)
    device = resolve_device(args.device, "--device")
    args.device = device.type
    set_threads(args.threads, "--threads")
    machine = {"platform": platform.platform(), "processor": platform.processor(),
               "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "torch": torch.__version__, "device": str(device),
               "load_average": os.getloadavg()}
    if device.type == "cuda":
        machine["gpu"] = torch.cuda.get_device_name(device)
    reports = []
    for n in args.grid:
        reports.append(benchmark_grid(n, args, device))
        print_table(reports[-1])
    out = {"machine": machine, "results": reports}
    write_json(Path(args.out), out)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
