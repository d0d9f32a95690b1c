"""Solver speed on the paper-scale problem against scikit-learn (and celer, if installed).

The problem: the built-in synthetic flame, 8 views of 320x240, silhouette rays x visual-hull
voxels on an N^3 grid, trilinear assembled operator A (float32 CSR), data P (N_rays, 3), and
lambda = l1_rel * max(A^T P). Every method runs on the identical (A, P, lambda) under a time
budget; its objective 0.5||A x - P||^2 + lambda * sum(x) is traced in float64 (the tracing time
is not counted) and the time to a relative objective gap of 1e-4 and 1e-6 against the best
objective any method reached is reported. Also: the machine's memory bandwidth and the time of
one A x and one A^T y against the bound bytes(A) / bandwidth.

    PYTHONPATH=. python scripts/benchmark.py --grid 64 --l1-rel 1e-3 --budget 60 --dump out/
"""

from __future__ import annotations

import json
import os
import platform
import queue as queue_module
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from flamerecon.cli import ArgumentParser, run_script
from flamerecon.device import resolve_device
from flamerecon.grid import VoxelGrid
from flamerecon.hull import visual_hull
from flamerecon.projector import assemble, camera_rays
from flamerecon.scenes import load_scene
from flamerecon.silhouettes import silhouettes
from flamerecon.solvers import SOLVERS, Problem, lambda_max, make_solver

TARGETS = (1e-4, 1e-6)
DEFAULT_SOLVER = "fista"
PEERS = ("sklearn_lasso", "sklearn_lassolars", "celer_lasso")


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


class Tracer:
    """Records (solver seconds, float64 objective) pairs; its own time is not counted.

    The objective is evaluated in float64 on the operator's device (a float64 copy of A), so
    tracing a GPU solve costs little and a CPU peer's numpy iterate is scored the same way.
    """

    def __init__(self, A64: torch.Tensor, P64: torch.Tensor, lam: float) -> None:
        self.A64, self.P64, self.lam = A64, P64, lam
        self.start = time.perf_counter()
        self.overhead = 0.0
        self.trace: list[tuple[float, float]] = []

    def objective(self, x) -> float:
        x = torch.as_tensor(x).to(self.P64).reshape(self.A64.shape[1], -1)
        r = self.A64 @ x - self.P64
        return float(0.5 * (r * r).sum() + self.lam * x.abs().sum())

    def record(self, x) -> None:
        t = time.perf_counter()
        self.trace.append((t - self.start - self.overhead, self.objective(x)))
        self.overhead += time.perf_counter() - t


def run_ours(name: str, problem: Problem, tracer: Tracer, budget: float) -> dict:
    solver = make_solver(name, tol=1e-12, max_iters=10**7, check_every=10, max_seconds=budget)
    tracer.start = time.perf_counter()
    result = solver.solve(problem, callback=lambda it, x, info: tracer.record(x))
    return {"iterations": result.iterations, "x": result.x.cpu().numpy()}


def run_chunked(estimator_cls, A_csc, P64: np.ndarray, lam: float, tracer: Tracer,
                budget: float) -> dict:
    """A coordinate-descent peer (scikit-learn or celer ``Lasso``) with warm-started fits of
    growing epoch counts, traced after each fit (the peers have no iteration callback)."""
    model = estimator_cls(alpha=lam / A_csc.shape[0], positive=True, fit_intercept=False,
                          warm_start=True, tol=1e-14, max_iter=5)
    epochs, chunk = 0, 5
    tracer.start = time.perf_counter()
    while tracer.trace == [] or tracer.trace[-1][0] < budget:
        model.set_params(max_iter=chunk)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(A_csc, P64)
        epochs += chunk
        tracer.record(np.asarray(model.coef_).T)
        chunk = int(np.ceil(chunk * 1.5))
    return {"iterations": epochs, "x": np.asarray(model.coef_).T}


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
    import multiprocessing as mp

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


def seconds_to(trace: list[tuple[float, float]], best: float, target: float) -> float | None:
    for seconds, f in trace:
        if (f - best) / abs(best) <= target:
            return seconds
    return None


def write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as f:
        json.dump(data, f, indent=2)
    os.replace(f.name, path)


def dump(folder: Path, A, P: np.ndarray, lam: float, x: np.ndarray) -> None:
    """A.npz (scipy CSR) and problem.npz (P, lam, x), each written whole or not at all."""
    import scipy.sparse as sp

    folder.mkdir(parents=True, exist_ok=True)
    for name, save in (("A.npz", lambda f: sp.save_npz(f, A)),
                       ("problem.npz", lambda f: np.savez(f, P=P, lam=lam, x=x))):
        with tempfile.NamedTemporaryFile(dir=folder, suffix=".tmp", delete=False) as f:
            save(f)
        os.replace(f.name, folder / name)


def benchmark_grid(n: int, args, device: torch.device) -> dict:
    t0 = time.perf_counter()
    built = build_problem(n, device)
    A, P = built["A"], built["P"]
    N, M = A.shape
    lam = args.l1_rel * lambda_max(A, P)
    print(f"grid {n}^3: {N} rays x {M} hull voxels, nnz {A.nnz}, {A.nbytes() / 1e6:.0f} MB per "
          f"copy, assembled in {built['assembly_seconds']:.1f} s (setup {time.perf_counter() - t0:.0f} s)")

    bw = memory_bandwidth(device)
    x1 = torch.rand(M, P.shape[1], device=device)
    y1 = torch.rand(N, P.shape[1], device=device)
    t_ax, t_aty = timed(lambda: A.forward(x1), device), timed(lambda: A.adjoint(y1), device)
    bound = A.nbytes() / bw
    print(f"bandwidth {bw / 1e9:.1f} GB/s; A x {t_ax * 1e3:.1f} ms, A^T y {t_aty * 1e3:.1f} ms, "
          f"bound {bound * 1e3:.1f} ms each; pair at {(t_ax + t_aty) / (2 * bound):.1f}x the bound")

    A64_device, P64_device = A.A.to(torch.float64), P.double()  # the tracers' objective
    problem = Problem(A, P, lam, grid_shape=built["grid"].shape, voxel_index=built["voxel_index"])
    runs: dict[str, dict] = {}
    traces: dict[str, list] = {}
    for name in args.solvers:
        tracer = Tracer(A64_device, P64_device, lam)
        runs[name] = run_ours(name, problem, tracer, args.budget)
        traces[name] = tracer.trace
        print(f"  {name}: {runs[name]['iterations']} iterations, {tracer.trace[-1][0]:.1f} s")
    peers = {"sklearn_lasso": "sklearn.linear_model"} if "sklearn_lasso" in args.peers else {}
    if "celer_lasso" in args.peers:
        try:
            import celer  # noqa: F401

            peers["celer_lasso"] = "celer"
        except ImportError:
            print("  celer: not installed, skipped")
    if peers or "sklearn_lassolars" in args.peers:  # the peers' input (CPU, float64)
        A64, P64 = A.to_scipy().astype(np.float64), P.cpu().double().numpy()
    if peers:
        A_csc = A64.tocsc()
    for label, module in peers.items():
        estimator = __import__(module, fromlist=["Lasso"]).Lasso
        tracer = Tracer(A64_device, P64_device, lam)
        runs[label] = run_chunked(estimator, A_csc, P64, lam, tracer, args.budget)
        traces[label] = tracer.trace
        print(f"  {label}: {runs[label]['iterations']} epochs, {tracer.trace[-1][0]:.1f} s")
    skipped = {}
    if "sklearn_lassolars" in args.peers:
        fits, why = lars_fits(N, M)
        if not fits:
            skipped["sklearn_lassolars"] = why
        else:
            tracer = Tracer(A64_device, P64_device, lam)
            got = run_lassolars(A64, P64, lam, args.budget)
            if got is None:
                skipped["sklearn_lassolars"] = f"did not finish within the {args.budget:g} s budget"
            else:
                tracer.trace = [(got["seconds"], tracer.objective(got["x"]))]
                runs["sklearn_lassolars"], traces["sklearn_lassolars"] = got, tracer.trace
    for label, reason in skipped.items():
        print(f"  {label}: skipped ({reason})")

    best = min(f for trace in traces.values() for _, f in trace)
    methods = {}
    for name, trace in traces.items():
        methods[name] = {
            **{f"seconds_to_{t:.0e}".replace("e-0", "e-"): seconds_to(trace, best, t)
               for t in TARGETS},
            "iterations": runs[name]["iterations"],
            "objective": trace[-1][1],
            "seconds": trace[-1][0],
            "trace": [[round(s, 4), f] for s, f in trace],
        }
    report = {
        "grid": [n, n, n], "rays": N, "voxels": M, "nnz": A.nnz, "l1_rel": args.l1_rel,
        "lambda": lam, "best_objective": best, "budget_seconds": args.budget,
        "assembly_seconds": built["assembly_seconds"],
        "bandwidth_GBps": bw / 1e9, "seconds_Ax": t_ax, "seconds_ATy": t_aty,
        "seconds_bound_each": bound, "methods": methods, "skipped": skipped,
    }
    if args.dump is not None:
        folder = Path(args.dump) if len(args.grid) == 1 else Path(args.dump) / f"grid{n}"
        dump(folder, A.to_scipy(), P.cpu().numpy(), lam,
             runs[DEFAULT_SOLVER]["x"] if DEFAULT_SOLVER in runs else np.zeros((M, P.shape[1])))
    return report


def print_table(report: dict) -> None:
    def fmt(v):
        return "  > budget" if v is None else f"{v:10.2f}"

    print(f"\n{report['grid'][0]}^3, lambda = {report['l1_rel']:g} max(A^T P), "
          f"best objective {report['best_objective']:.8g}")
    print(f"{'method':<20}{'s to 1e-4':>10}{'s to 1e-6':>10}{'iters':>8}{'objective':>16}")
    for name, m in report["methods"].items():
        print(f"{name:<20}{fmt(m['seconds_to_1e-4'])}{fmt(m['seconds_to_1e-6'])}"
              f"{m['iterations']:>8}{m['objective']:>16.8g}")


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
    parser = ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", type=int, nargs="+", default=[64], help="grid sizes N (N^3)")
    parser.add_argument("--l1-rel", type=float, default=1e-3, help="lambda / max(A^T P)")
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per method")
    parser.add_argument("--solvers", nargs="+", default=["fista"], help="ours, e.g. fista lbfgsb")
    parser.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS,
                        help="peers to time (default: all; installed ones run)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--out", default="benchmark.json")
    parser.add_argument("--dump", default=None, help="folder for A.npz, problem.npz, benchmark.json")
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args) -> None:
    check_args(args)
    device = resolve_device(args.device, "--device")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
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
    if args.dump is not None:
        write_json(Path(args.dump) / "benchmark.json", out)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
