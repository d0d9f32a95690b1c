"""Solvers for the nonnegative LASSO, registered by name (``solver=<name>``)."""

from .base import SOLVERS, LinearOperator, Problem, SolveResult, Solver, make_solver, register
from . import fista  # noqa: F401  (registers)

__all__ = ["SOLVERS", "LinearOperator", "Problem", "SolveResult", "Solver", "make_solver", "register"]
