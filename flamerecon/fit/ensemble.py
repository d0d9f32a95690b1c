"""What the cameras leave free: densities that fit the data about as well as the
reconstruction does, solved from it, whose spread is the confidence of
:mod:`flamerecon.evaluate.uncertainty`.

Member kinds (``uncertainty.members``):

- ``cameras``: each training camera left out in turn, its pixel rows dropped from the fit (the
  visual hull of every camera kept: its silhouette is data too); the same options, warm-started
  from the reconstruction;
- ``weights``: the solver's weights (``l1_rel`` or ``l1``, and its prior: ``tv`` or ``smooth``)
  each multiplied and divided by ``weight_factor`` in turn, the range cross-validation found
  about equally good on ScalarFlow (l1_rel 0.03-0.1, tv 0.015-0.05).

A member solve has the reconstruction's options (debias included) with ``iterations`` steps
(None: the solver's ``max_iters``) and no weight selection (the weights chosen stay). Each
member is a density on the reconstruction's hull; the sub-voxel shifts of
``uncertainty.shift_voxels`` need no solve (:mod:`flamerecon.evaluate.uncertainty`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import torch

from flamerecon.arguments import fields
from flamerecon.errors import ConfigError, SolveDiverged
from flamerecon.evaluate.uncertainty import Confidence
from flamerecon.fit.reconstruct import fit
from flamerecon.fit.uncertainty_options import UncertaintyOptions
from flamerecon.fit.weight_selection import row_subset
from flamerecon.progress import Progress

#: solver options that weigh a prior, perturbed by the ``weights`` members when the solver has one
PRIOR_WEIGHTS = ("tv", "smooth")


@dataclass
class Ensemble:
    """Member densities on a reconstruction's hull: ``members`` (K, M, C), each labelled in
    ``labels`` (``"cameras:train00"``, ``"weights:tv*2"``), and the ``seconds`` they took."""

    members: torch.Tensor
    labels: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def __post_init__(self) -> None:
        fields(self)

    def groups(self) -> list[str]:
        """Each member's kind (``cameras``, ``weights``)."""
        return [label.split(":", 1)[0] for label in self.labels]


def member_options(options, uncertainty: UncertaintyOptions):
    """The reconstruction's ``options`` for a member solve: ``iterations`` steps, no weight
    selection (the chosen weights stay)."""
    options = options.replace(select=replace(options.select, auto=False))
    if uncertainty.iterations is not None and "max_iters" in options.solver.params:
        options = options.replace(solver=options.solver.with_values(max_iters=int(uncertainty.iterations)))
    return options


def weight_variants(solver, factor: float) -> list[tuple[str, dict]]:
    """(label, overrides) of the ``weights`` members of ``solver`` (SolverOptions): its L1
    weight (``l1`` when set, else ``l1_rel``) and its prior weight (:data:`PRIOR_WEIGHTS`, when
    it has one and it is not 0) times and over ``factor``."""
    names = ["l1" if solver.l1 is not None else "l1_rel"]
    names += [k for k in PRIOR_WEIGHTS if solver.params.get(k)]
    now = {"l1": solver.l1, "l1_rel": solver.l1_rel, **solver.params}
    out = []
    for name in names:
        if not now.get(name):
            continue  # a zero weight has no range to perturb
        for f, sign in ((factor, "*"), (1.0 / factor, "/")):
            out.append((f"weights:{name}{sign}{factor:g}", {name: float(now[name]) * f}))
    return out


def solve_ensemble(setup, options, x: torch.Tensor, uncertainty: UncertaintyOptions) -> Ensemble:
    """The members of ``uncertainty.members`` for the reconstruction ``x`` (M, C) found on
    ``setup`` (:class:`~flamerecon.fit.build.Setup`) with ``options`` (the fit's, weights as
    chosen). Logs a progress line per member."""
    base = member_options(options, uncertainty)
    plans: list[tuple[str, object, object]] = []  # (label, setup, options)
    kinds = uncertainty.members.split("+")
    if "cameras" in kinds:
        if len(setup.train) < 2:
            raise ConfigError(f"uncertainty.members: leaving cameras out needs at least two training views, "
                             f"got {len(setup.train)}; use uncertainty.members=weights")
        for k, v in enumerate(setup.train):
            rows = (setup.row_view != k).nonzero().squeeze(1)
            fold = replace(setup, operator=row_subset(setup.operator, rows), pixels=setup.pixels[rows].contiguous(),
                           row_view=setup.row_view[rows],
                           row_pixel=None if setup.row_pixel is None else setup.row_pixel[rows])
            plans.append((f"cameras:{setup.scene.views[v]}", fold, base))
    if "weights" in kinds:
        for label, change in weight_variants(base.solver, float(uncertainty.weight_factor)):
            plans.append((label, setup, base.replace(solver=base.solver.with_values(**change))))
    started = time.perf_counter()
    progress = Progress("uncertainty ensemble", len(plans), unit="member")
    members = []
    for n, (label, fold, opts) in enumerate(plans, 1):
        members.append(fit(fold, opts, x).result.x)
        progress.update(n, label)
    stacked = torch.stack(members) if members else x.new_zeros(0, *x.shape)
    if not math.isfinite(float(stacked.sum())):
        raise SolveDiverged("uncertainty: a member solve diverged (NaN or Inf); try uncertainty.members=weights "
                            "or fewer uncertainty.iterations")
    return Ensemble(stacked, [label for label, _, _ in plans], time.perf_counter() - started)


def confidence(setup, options, x: torch.Tensor, uncertainty: UncertaintyOptions | None = None) -> Confidence:
    """The :class:`~flamerecon.evaluate.uncertainty.Confidence` of the reconstruction ``x``
    (M, C) found on ``setup`` with ``options``: the ensemble of ``uncertainty`` (default:
    ``options.uncertainty``) solved (:func:`solve_ensemble`), its shift and scale."""
    uncertainty = uncertainty or options.uncertainty
    found = solve_ensemble(setup, options, x, uncertainty)
    return Confidence(setup.grid, setup.voxel_index, setup.hull, x, found.members, found.groups(),
                      float(uncertainty.shift_voxels), float(uncertainty.scale), setup.step, found.seconds,
                      found.labels)
