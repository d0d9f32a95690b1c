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

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import os
import sys
import time

import flamerecon as fr
from flamerecon.fit.build import make_problem
from flamerecon.resources import config_dir
from flamerecon.run.cli import at_least, compose_train, run_script, script_parser
from flamerecon.run.config import options_from_config


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


def solver_entry(entry: str) -> tuple[str, str, dict]:
    """argparse type: ``NAME[:key=value,...]`` -> (entry, name, options with numbers parsed)."""
    name, _, rest = entry.partition(":")
    options = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        try:
            options[key] = int(value) if value.lstrip("-").isdigit() else float(value)
        except ValueError:
            sep = ""
        if not sep or not key:
            raise argparse.ArgumentTypeError(f"'{entry}': '{item}' is not key=number; give NAME[:key=value,...]")
    if not (config_dir() / "solver" / f"{name}.yaml").is_file():
        raise argparse.ArgumentTypeError(f"'{entry}': unknown solver '{name}'; one of conf/solver/: "
                                         f"{', '.join(sorted(p.stem for p in (config_dir() / 'solver').glob('*.yaml')))}")
    return entry, name, options


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--solvers", nargs="+", type=solver_entry,
                        default=[solver_entry("fista_smooth"), solver_entry("pqn_smooth:max_iters=100")],
                        metavar="NAME[:key=value,...]", help="the solvers, each with its options")
    parser.add_argument("--frame", type=at_least(0), default=0, help="the synthetic flame's frame")
    parser.add_argument("--repeats", type=at_least(1), default=2, help="solves of each solver")
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def solver_of(name: str, overrides: dict):
    """The options of ``solver=NAME`` (``conf/solver/<name>.yaml``) with ``overrides`` on top."""
    cfg = compose_train([f"solver={name}", *(f"solver.{k}={v}" for k, v in overrides.items())], "synthetic")
    return options_from_config(cfg).solver


def run(args) -> None:
    scene = fr.load_scene("synthetic", frame=args.frame)
    options = fr.ReconstructionOptions()
    setup = fr.build(scene, options)
    print(f"frame {args.frame}: {setup.operator.shape[0]} rays x {setup.operator.shape[1]} voxels")
    for _ in range(args.repeats):
        for entry, name, overrides in args.solvers:
            solver_options = solver_of(name, overrides)
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
