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

With the cameras' pose offsets of a capture's calibration (:mod:`flamerecon.fit.pose_uncertainty`)
two ``poses`` members are solved whatever ``uncertainty.members`` says: the training pixels as
the training cameras moved by plus, then minus, their offsets would record them
(:func:`posed_pixels`): what the cameras' pose uncertainty leaves free in the density.

A member solve has the reconstruction's options (debias included) with ``iterations`` steps
(None: the solver's ``max_iters``) and no weight selection (the weights chosen stay). Each
member is a density on the reconstruction's hull; the sub-voxel shifts of
``uncertainty.shift_voxels`` need no solve (:mod:`flamerecon.evaluate.uncertainty`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import torch

from flamerecon.arguments import fields
from flamerecon.errors import ConfigError, SolveDiverged
from flamerecon.evaluate.pose_spread import PoseSpread
from flamerecon.evaluate.uncertainty import Confidence
from flamerecon.fit.build import fit_pixels as build_pixels
from flamerecon.fit.pose_uncertainty import offsets_of, spread
from flamerecon.fit.reconstruct import fit
from flamerecon.fit.uncertainty_options import UncertaintyOptions
from flamerecon.fit.weight_selection import row_subset
from flamerecon.geometry.cameras import camera_subset, cameras_to
from flamerecon.operators.projector import render_image
from flamerecon.progress import Progress

log = logging.getLogger(__name__)

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


def posed_pixels(setup, x: torch.Tensor, poses: PoseSpread) -> list[tuple[str, torch.Tensor]]:
    """(label, pixels (N, C)) of the two ``poses`` members of the reconstruction ``x`` (M, C)
    on ``setup``: the training pixels as every training camera with a pose offset would record
    them moved by plus (then minus) its offset, to its share: ``pixels + sqrt(share) (render
    moved - render)`` on its rows; none when no training camera has an offset."""
    views = [setup.scene.views[v] for v in setup.train]
    if not any(v in poses.views for v in views):
        return []
    cams = cameras_to(camera_subset(setup.scene.cameras, setup.train), setup.pixels.device)
    rows = build_pixels(setup.options.projector.rays, setup.grid, cams, setup.hull, setup.masks[setup.train])
    flat = rows.reshape(-1).nonzero().squeeze(1)
    density = setup.volume(x)
    base = render_image(density, setup.grid, cams, setup.step)
    out = []
    for sign, label in ((0, "poses:+"), (1, "poses:-")):
        moved = base.clone()
        for k, view in enumerate(views):
            if view in poses.views:
                share = float(poses.share[poses.views.index(view)])
                cam = poses.moved(view, camera_subset(cams, [k]))
                moved[k] = base[k] + share ** 0.5 * (render_image(density, setup.grid, camera_subset(
                    cameras_to(cam, density.device), [sign]), setup.step)[0] - base[k])
        change = (moved - base).permute(0, 2, 3, 1).reshape(-1, base.shape[1])[flat]
        out.append((label, setup.pixels + change.to(setup.pixels)))
    return out


def solve_ensemble(setup, options, x: torch.Tensor, uncertainty: UncertaintyOptions,
                   poses: PoseSpread | None = None) -> Ensemble:
    """The members of ``uncertainty.members`` for the reconstruction ``x`` (M, C) found on
    ``setup`` (:class:`~flamerecon.fit.build.Setup`) with ``options`` (the fit's, weights as
    chosen), and with ``poses`` the two ``poses`` members (:func:`posed_pixels`). Logs a
    progress line per member."""
    base = member_options(options, uncertainty)
    plans: list[tuple[str, object, object]] = []  # (label, setup, options)
    if poses is not None:
        plans += [(label, replace(setup, pixels=pixels), base) for label, pixels in posed_pixels(setup, x, poses)]
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


def confidence(setup, options, x: torch.Tensor, uncertainty: UncertaintyOptions | None = None,
               calibration: dict | None = None) -> Confidence:
    """The :class:`~flamerecon.evaluate.uncertainty.Confidence` of the reconstruction ``x``
    (M, C) found on ``setup`` with ``options``: the ensemble of ``uncertainty`` (default:
    ``options.uncertainty``) solved (:func:`solve_ensemble`), its shift and scale, and the
    cameras' pose uncertainty that the reconstruction's ``calibration`` record holds
    (:func:`~flamerecon.fit.pose_uncertainty.offsets_of`, the cameras it refined as fitted;
    none without)."""
    uncertainty = uncertainty or options.uncertainty
    started = time.perf_counter()
    offsets = offsets_of(calibration)
    if not offsets and (calibration or {}).get("frames"):
        log.warning("the capture's calibration %s holds no pose offsets: this confidence leaves the cameras' pose "
                    "errors out; reconstruct with calibration.offsets=true to measure them (once per capture)",
                    calibration.get("file"))
    fitted = set((calibration or {}).get("cameras") or {})  # the cameras the camera fit refined
    poses = None if not offsets else spread(setup.scene.cameras, list(setup.scene.views), offsets, setup.grid, fitted)
    found = solve_ensemble(setup, options, x, uncertainty, poses)
    return Confidence(setup.grid, setup.voxel_index, setup.hull, x, found.members, found.groups(),
                      float(uncertainty.shift_voxels), float(uncertainty.scale), setup.step,
                      time.perf_counter() - started, found.labels, poses)
