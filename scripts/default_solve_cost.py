"""What the default run's solve costs with each solver: products over A and seconds.

Builds the default ``python train.py`` problem (synthetic flame, frame ``--frame``) through the
Python API, then solves it with each ``--solvers`` entry (``NAME[:key=value,...]``, e.g.
``fista_smooth`` or ``pqn_smooth:max_iters=100``) ``--repeats`` times in turn (interleaved,
so that a change of load hits them alike), counting every product of the projector A (power
iterations, line searches and stopping checks included). Prints per solve the iterations,
products of A, seconds, final objective and relative duality gap, with the load average.

    PYTHONPATH=. python scripts/default_solve_cost.py --solvers fista_smooth pqn_smooth:max_iters=100
"""

from __future__ import annotations

import os
import sys
import time

import flamerecon as fr
from flamerecon.fit.build import make_problem
from flamerecon.run.cli import ArgumentParser, run_script


class Counted:
    """The projector, counting its products (A x and A^T y alike)."""

    def __init__(self, A) -> None:
        self.A, self.shape, self.products = A, A.shape, 0

    def forward(self, x):
        self.products += 1
        return self.A.forward(x)

    def adjoint(self, y):
        self.products += 1
        return self.A.adjoint(y)


def parse(entry: str) -> tuple[str, dict]:
    """``NAME[:key=value,...]`` -> (name, options with numbers parsed)."""
    name, _, rest = entry.partition(":")
    options = {}
    for item in filter(None, rest.split(",")):
        key, value = item.split("=")
        options[key] = int(value) if value.lstrip("-").isdigit() else float(value)
    return name, options


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--solvers", nargs="+", default=["fista_smooth", "pqn_smooth:max_iters=100"])
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args) -> None:
    scene = fr.load_scene("synthetic", frame=args.frame)
    options = fr.ReconstructionOptions()
    setup = fr.build(scene, options)
    print(f"frame {args.frame}: {setup.operator.shape[0]} rays x {setup.operator.shape[1]} voxels")
    for _ in range(args.repeats):
        for entry in args.solvers:
            name, overrides = parse(entry)
            solver_options = options.solver.with_values(name=name, **overrides)
            problem, solver, _ = make_problem(solver_options, setup)
            problem.A = counted = Counted(setup.operator)  # a fresh one: no cached norm
            start = time.perf_counter()
            result = solver.solve(problem)
            seconds = time.perf_counter() - start
            gap = result.history[-1].get("rel_gap", float("nan")) if result.history else float("nan")
            print(f"  {entry:<28} {result.iterations:>5} it {counted.products:>6} products of A "
                  f"{seconds:7.2f} s  objective {result.objective:.6f}  rel. gap {gap:.1e}  "
                  f"load {os.getloadavg()[0]:.2f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
