"""How many passes over A a first-order method needs with each step metric or acceleration.

On the problem :mod:`scripts.benchmark` dumps (``grid<N>/A.npz``, ``problem.npz``,
``reference.npz``: run ``benchmark.py --grid N`` once first), from x = 0. FISTA variants iterate
x+ = max(0, y - S (A^T (A y - b) + lambda)) with momentum, S a per-voxel step:

- ``lipschitz``: S = 1 / ||A||^2 (``solver=fista``);
- ``sqs``: S = 1 / d, d = |A|^T |A| 1 (the separable quadratic surrogate: diag(d) >= A^T A);
- ``blend:c``: S = 1 / max(d, c ||A||^2) (no step longer than 1 / (c ||A||^2));
- ``sqs/a``: S = a / d (a > 1: longer than the surrogate allows, kept only by the restart).

and restarts its momentum when the step goes uphill in its metric ((y - x+)^T S^-1 (x+ - x) > 0,
O'Donoghue and Candes). Others:

- ``anderson:K[:metric]``: projected gradient with step S of ``metric`` (default ``lipschitz``),
  Anderson-extrapolated per column every K + 1 iterates, kept where it lowers F (Bertrand and
  Massias 2021; one A x more per extrapolation);
- ``solver:NAME[:key=value,...]``: a registered solver (e.g. ``solver:pqn``, ``solver:lbfgsb``),
  every product it makes counted, its stopping checks included.

Every ``--every`` iterations the float64 objective is recomputed (its time not counted) and the
iterations, products of A or A^T (setup included: 60 for the power iteration of ||A||^2) and
seconds to a relative gap (F - f*) / f* of 1e-4 and 1e-6 against the certified reference f* are
printed, with the load average ("extra": restarts, accepted extrapolations, or nothing).

    PYTHONPATH=. python scripts/preconditioning_study.py --grid 64 --iters 3000 --threads 2 \
        --variants lipschitz sqs blend:0.5 sqs/1.5 anderson:5 solver:pqn solver:lbfgsb
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import os
import sys
import time
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np
import torch
from benchmark import CACHE, objectives

from flamerecon.device import set_threads
from flamerecon.errors import ConfigError
from flamerecon.operators import CsrOperator, norm_sq
from flamerecon.run.cli import run_script, script_parser
from flamerecon.solvers import Problem, make_solver

TARGETS = (1e-4, 1e-6)


def load(folder: Path) -> tuple[CsrOperator, torch.Tensor, float, float]:
    """The dumped problem: A (float32), P (N, C), lambda, and the reference f* (summed)."""
    import scipy.sparse as sp

    if not (folder / "A.npz").exists():
        raise ConfigError(f"{folder}: no dump; run scripts/benchmark.py --grid N first")
    A = sp.load_npz(folder / "A.npz").tocsr()
    coo = A.tocoo()
    op = CsrOperator.from_sorted_coo(torch.from_numpy(coo.row.astype(np.int64)),
                                     torch.from_numpy(coo.col.astype(np.int64)),
                                     torch.from_numpy(coo.data.astype(np.float32)), A.shape)
    problem = np.load(folder / "problem.npz")
    ref = np.load(folder / "reference.npz")
    return op, torch.from_numpy(problem["P"]).float(), float(problem["lam"]), float(ref["f"].sum())


def steps(variant: str, A: CsrOperator) -> tuple[torch.Tensor, int]:
    """The per-voxel step (M, 1) of ``variant`` and the products spent finding it."""
    d = A.adjoint(A.forward(torch.ones(A.shape[1], 1)))  # A >= 0: |A|^T |A| 1
    if variant == "lipschitz":
        return torch.full_like(d, 1.0 / (1.01 * norm_sq(A))), 60
    if variant == "sqs":
        return 1.0 / d, 2
    if variant.startswith("blend:"):
        c = float(variant.split(":")[1])
        return 1.0 / torch.maximum(d, torch.tensor(c * 1.01 * norm_sq(A))), 62
    if variant.startswith("sqs/"):
        return float(variant.split("/")[1]) / d, 2
    raise ConfigError(f"unknown variant {variant!r}")


def run_variant(variant: str, A: CsrOperator, b: torch.Tensor, lam: float, f_ref: float,
                A64: torch.Tensor, P64: torch.Tensor, iters: int, every: int) -> dict:
    """Iterate ``variant`` up to ``iters`` times or the last target; what it took to each."""
    if variant.startswith("solver:"):
        return run_solver(variant, A, b, lam, f_ref, A64, P64, iters, every)
    start = time.perf_counter()
    anderson = variant.startswith("anderson:")
    if anderson:  # anderson:K[:metric]
        parts = variant.split(":")
        K, variant = int(parts[1]), parts[2] if len(parts) > 2 else "lipschitz"
    S, setup_products = steps(variant, A)
    x = torch.zeros(A.shape[1], b.shape[1])
    y, t = x.clone(), 1.0
    hits: dict[float, tuple[int, float]] = {}
    overhead, restarts, gap, products = 0.0, 0, float("nan"), setup_products
    r = -b  # A x - b at the point the next gradient is taken (anderson: x itself)
    last: list[torch.Tensor] = []
    for k in range(1, iters + 1):
        if anderson:
            x = (x - S * (A.adjoint(r) + lam)).clamp_min_(0)
            r = A.forward(x) - b
            products += 2
            last = [*last[-K:], x]
            if len(last) == K + 1:
                x_e = extrapolate(last)
                r_e = A.forward(x_e) - b
                products += 1
                better = column_objective(r_e, x_e, lam) < column_objective(r, x, lam)
                x = torch.where(better, x_e, x)
                r = torch.where(better, r_e, r)
                restarts += int(better.sum())
                last = []
        else:
            grad = A.adjoint(A.forward(y) - b)
            products += 2
            x_new = (y - S * (grad + lam)).clamp_min_(0)
            if float(((y - x_new) * (x_new - x) / S).sum()) > 0:
                t, restarts = 1.0, restarts + 1
            t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t) ** 0.5)
            y = x_new + ((t - 1.0) / t_new) * (x_new - x)
            x, t = x_new, t_new
        if k % every == 0:
            tick = time.perf_counter()
            gap = (float(objectives(A64, P64, lam, x).sum()) - f_ref) / f_ref
            for target in TARGETS:
                if gap <= target and target not in hits:
                    hits[target] = (k, products, tick - start - overhead)
            overhead += time.perf_counter() - tick
            if len(hits) == len(TARGETS):
                break
    return {"hits": hits, "last_gap": gap, "iterations": k, "extra": restarts}


class Counted:
    """An operator that counts its products (A x and A^T y alike)."""

    def __init__(self, A) -> None:
        self.A, self.shape, self.products = A, A.shape, 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        self.products += 1
        return self.A.forward(x)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        self.products += 1
        return self.A.adjoint(y)


def run_solver(variant: str, A: CsrOperator, b: torch.Tensor, lam: float, f_ref: float,
               A64: torch.Tensor, P64: torch.Tensor, iters: int, every: int) -> dict:
    """``solver:NAME[:key=value,...]``: a registered solver, every product counted (its own
    stopping checks too), the objective recomputed at its checks (every ``every``)."""
    _, name, *rest = variant.split(":")
    options = dict(kv.split("=") for kv in rest[0].split(",")) if rest else {}
    options = {k: float(v) if "." in v or "e" in v else int(v) for k, v in options.items()}
    counted = Counted(A)
    hits: dict[float, tuple[int, int, float]] = {}
    state = {"overhead": 0.0, "gap": float("nan")}

    def record(it: int, x: torch.Tensor, info: dict) -> None:
        tick = time.perf_counter()
        state["gap"] = gap = (float(objectives(A64, P64, lam, x).sum()) - f_ref) / f_ref
        for target in TARGETS:
            if gap <= target and target not in hits:
                hits[target] = (it, counted.products, tick - start - state["overhead"])
        state["overhead"] += time.perf_counter() - tick
        if len(hits) == len(TARGETS):
            solver.max_seconds = 0.0  # stop at this check

    solver = make_solver(name, tol=0.0, max_iters=iters, check_every=every, **options)
    start = time.perf_counter()
    result = solver.solve(Problem(counted, b, lam), callback=record)
    return {"hits": hits, "last_gap": state["gap"], "iterations": result.iterations,
            "extra": 0}


def column_objective(r: torch.Tensor, x: torch.Tensor, lam: float) -> torch.Tensor:
    """F per column (1, C) in float64 from the residual r = A x - b (N, C) and x (M, C)."""
    return (0.5 * (r.double() ** 2).sum(0) + lam * x.double().sum(0)).unsqueeze(0)


def extrapolate(last: list[torch.Tensor]) -> torch.Tensor:
    """Anderson extrapolation per column from K + 1 iterates (M, C): the affine combination
    of the last K whose combined differences are least (Bertrand and Massias 2021)."""
    X = torch.stack(last, 0).double()  # (K + 1, M, C)
    U = X[1:] - X[:-1]  # (K, M, C)
    out = []
    for c in range(X.shape[2]):
        G = U[:, :, c] @ U[:, :, c].T
        G += 1e-10 * G.diagonal().max().clamp_min(1e-300) * torch.eye(G.shape[0], dtype=G.dtype)
        z = torch.linalg.solve(G, torch.ones(G.shape[0], dtype=G.dtype))
        out.append((z / z.sum()) @ X[1:, :, c])
    return torch.stack(out, 1).clamp_min(0).float()


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--variants", nargs="+",
                        default=["lipschitz", "sqs", "blend:0.1", "blend:0.3", "sqs/1.5", "sqs/2"])
    parser.add_argument("--iters", type=int, default=3000, help="at most, per variant")
    parser.add_argument("--every", type=int, default=10, help="objective every this many")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: the free cores)")
    parser.add_argument("--dump", default=str(CACHE))
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args) -> None:
    set_threads(args.threads)
    A, b, lam, f_ref = load(Path(args.dump) / f"grid{args.grid}")
    A64, P64 = A.A.to(torch.float64), b.double()
    print(f"grid {args.grid}^3: {A.shape[0]} rays x {A.shape[1]} voxels, lambda {lam:.6g}, "
          f"f* = {f_ref:.10g}; torch threads {torch.get_num_threads()}", flush=True)
    d = A.adjoint(A.forward(torch.ones(A.shape[1], 1)))[:, 0] / norm_sq(A)
    quantiles = torch.quantile(d, torch.tensor([0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0]))
    print("SQS diagonal / ||A||^2, quantiles 0 10 25 50 75 90 100 %: "
          + " ".join(f"{q:.2f}" for q in quantiles.tolist()), flush=True)
    print(f"{'variant':<12}{'it 1e-4':>8}{'prod 1e-4':>10}{'s 1e-4':>8}{'it 1e-6':>8}"
          f"{'prod 1e-6':>10}{'s 1e-6':>8}{'extra':>9}{'last gap':>10}  load")
    for variant in args.variants:
        got = run_variant(variant, A, b, lam, f_ref, A64, P64, args.iters, args.every)
        cells = []
        for target in TARGETS:
            if target in got["hits"]:
                k, products, s = got["hits"][target]
                cells += [f"{k:>8}", f"{products:>10}", f"{s:>8.1f}"]
            else:
                cells += [f"{'-':>8}", f"{'-':>10}", f"{'-':>8}"]
        print(f"{variant:<12}{''.join(cells)}{got['extra']:>9}{got['last_gap']:>10.1e}  "
              f"{os.getloadavg()[0]:.2f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
