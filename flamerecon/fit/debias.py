"""Undo the shrinkage of a penalised solve: L1 and TV pull every voxel towards zero, so the
fitted density under-predicts its own training views (on ScalarFlow by 4-12 %).

- ``gain``: one least-squares gain per colour channel of the training rows, ``g = <A x, b> /
  <A x, A x>``, multiplies the density (the model is linear, so its renders scale alike);
  the structure of the solution is kept, only its level is unbiased (a relaxed LASSO along x);
- ``refit``: ``iterations`` steps of unpenalised projected gradient (FISTA with l1 = 0) from
  the solution on the same rows: a few steps restore contrast, many fit the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from flamerecon.fit.option_rules import check_section
from flamerecon.solvers import LinearOperator, Problem, make_solver


@dataclass(frozen=True)
class DebiasOptions:
    """``method``: none | gain | refit; ``iterations``: refit steps."""

    method: str = "none"
    iterations: int = 10

    def __post_init__(self) -> None:
        check_section("debias", self)


def training_gain(A: LinearOperator, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Per-channel least-squares gain (C,) of the predictions A x (N, C) against b (N, C);
    1 where a channel predicts nothing."""
    ax = A.forward(x).double()
    num, den = (ax * b.double()).sum(0), (ax * ax).sum(0)
    return torch.where(den > 0, num / den.clamp_min(1e-300), torch.ones_like(den)).to(x.dtype)


def debias(options: DebiasOptions, A: LinearOperator, b: torch.Tensor, x: torch.Tensor
           ) -> tuple[torch.Tensor, dict]:
    """The debiased density (M, C) and what was done (for metrics.json): ``{"method", "gain"}``
    (the per-channel gain, ``gain``) or ``{"method", "iterations"}`` (``refit``)."""
    if options.method == "none":
        return x, {"method": "none"}
    if options.method == "gain":
        gain = training_gain(A, b, x).clamp_min(0)
        return x * gain, {"method": "gain", "gain": [float(g) for g in gain]}
    solver = make_solver("fista", max_iters=int(options.iterations), tol=0.0,
                         check_every=int(options.iterations))
    result = solver.solve(Problem(A, b, 0.0), x0=x)
    return result.x, {"method": "refit", "iterations": result.iterations}
