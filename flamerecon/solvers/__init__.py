"""Solvers for the nonnegative LASSO, registered by name (``solver=<name>``)."""

from . import adam, cgls, fista, lars, sart  # noqa: F401  (registers)
from .base import SOLVERS, LinearOperator, Problem, Solver, SolveResult, make_solver, register

__all__ = ["SOLVERS", "LinearOperator", "Problem", "SolveResult", "Solver", "make_solver", "register"]
