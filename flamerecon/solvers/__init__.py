"""Solvers for the nonnegative LASSO, registered by name (``solver=<name>``)."""

from flamerecon.solvers import (  # noqa: F401  (registers)
    adam,
    cgls,
    fista,
    fista_smooth,
    lars,
    lbfgsb,
    mart,
    newton_cg,
    pqn,
    primal_dual_tv,
    sart,
    ssnal,
)
from flamerecon.solvers.base import (
    SOLVERS,
    LinearOperator,
    Problem,
    Solver,
    SolveResult,
    lambda_max,
    make_solver,
    register,
    resolve_l1,
)

__all__ = ["SOLVERS", "LinearOperator", "Problem", "SolveResult", "Solver", "lambda_max",
           "make_solver", "register", "resolve_l1"]
