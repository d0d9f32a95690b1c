"""A 3D gradient-L2 (Laplacian) smoothness penalty between neighbouring hull voxels:

    min 0.5||A x - b||^2 + 0.5 s ||D x||^2 + l1 sum(x),   x >= 0

solved exactly as a nonnegative LASSO on the stacked system [A; sqrt(s) D] x ~ [b; 0], so the
duality-gap stopping rule of the LASSO solvers carries over unchanged: ``fista_smooth``
(:class:`Fista` on it) and ``pqn_smooth`` (:class:`ProjectedQuasiNewton` on it).
"""

from __future__ import annotations

import torch

from flamerecon.operators import StackedOperator, hull_gradient
from flamerecon.solvers.base import Problem, power_norm_sq, register
from flamerecon.solvers.fista import Fista
from flamerecon.solvers.pqn import ProjectedQuasiNewton


class SmoothnessPrior:
    """The penalty as a mixin before a LASSO solver class. ``smooth`` is relative:
    s = smooth * ||A||^2 / ||D||^2, so smooth = 1 weighs the penalty like the data term in
    operator norm. Needs ``problem.grid_shape`` and ``problem.voxel_index``. Other options as
    the solver's.
    """

    def __init__(self, smooth: float = 0.01, **options: object) -> None:
        super().__init__(**options)
        if float(smooth) < 0:
            raise ValueError(f"solver.smooth must be >= 0, got {smooth}")
        self.smooth = float(smooth)

    def stacked(self, problem: Problem) -> tuple[Problem, float]:
        """The stacked problem [A; sqrt(s) D] x ~ [b; 0] and a Lipschitz bound of its
        gradient, 1.01 (||A||^2 + s ||D||^2); keeps D and s for :meth:`report`."""
        if problem.grid_shape is None or problem.voxel_index is None:
            raise ValueError(f"solver={self.name} needs the hull geometry: Problem.grid_shape "
                             "and Problem.voxel_index are not set")
        A, b = problem.A, problem.b
        L_A = power_norm_sq(A, A.shape[1], b.device, b.dtype)
        D = hull_gradient(problem.grid_shape, problem.voxel_index.to(b.device))
        L_D = power_norm_sq(D, D.shape[1], b.device, b.dtype) if D.shape[0] else 0.0
        s = self.smooth * L_A / L_D if L_D > 0 else 0.0
        self.D, self.s = D, s
        b_aug = torch.cat([b, torch.zeros(D.shape[0], b.shape[1], dtype=b.dtype, device=b.device)])
        return Problem(StackedOperator(A, D, s**0.5), b_aug, problem.l1), 1.01 * (L_A + s * L_D)

    def report(self, it: int) -> dict[str, float]:
        """The solver's measures of the stacked problem, its data term split into the fit and
        the smoothness penalty."""
        info = super().report(it)
        penalty = 0.5 * self.s * float((self.D.forward(self.x).double() ** 2).sum())
        info.update(smooth=penalty, data=info["data"] - penalty, smooth_weight=self.s)
        return info


@register("fista_smooth")
class FistaSmooth(SmoothnessPrior, Fista):
    """FISTA (step 1 / (||A||^2 + s ||D||^2)) on the stacked problem."""

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        augmented, lipschitz = self.stacked(problem)
        return super().set_up(augmented, x, resume, lipschitz=lipschitz)


@register("pqn_smooth")
class PqnSmooth(SmoothnessPrior, ProjectedQuasiNewton):
    """Projected L-BFGS on the stacked problem."""

    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        return super().set_up(self.stacked(problem)[0], x, resume)
