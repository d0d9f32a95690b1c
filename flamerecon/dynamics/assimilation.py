"""The simulator fitted to a window of frames: the images, not the reconstructed densities, are
the data.

Over the frames t - W .. t of a sequence (W = ``window``), the simulation
(:mod:`flamerecon.dynamics.simulation`) starts from frame t - W's reconstruction x_{t-W} and a
velocity u_0 = P(U c) (a control grid c of ``control`` cells along the simulated box's longest
side, trilinear in between (U), projected divergence-free (P)), and steps W frames with the
buoyancy b, re-injecting each frame's source (frame s's reconstruction in the inflow region:
the bottom ``inflow`` fraction of the box along ``up`` where the smoke is). c and b minimise

    sum_{s=1..W} [0.5 ||A_s x_s - b_s||^2 / ||b_s||^2 + outside * 0.5 ||x_s off hull_s||^2 / ||x_0||^2] / r0_s / W
        + smooth * R(c)

with A_s, b_s frame t - W + s's operator and training pixels, r0_s the relative residual of the
previous frame's reconstruction not moved (the scale the motion has to explain, as in
:mod:`flamerecon.dynamics.flow`), R the control grid's squared velocity gradient (1/frame^2),
by L-BFGS through the simulation (autograd through advection, buoyancy and the projection; the
projector's adjoint as its gradient). Nothing after frame t enters. Where no prediction reads
the fit (the buoyancy held and ``start="flow"``), it is skipped: the record keeps the window's
residuals of the start velocity.

The defaults were chosen on ScalarFlow start frames 9 and 14 (docs/results.md, "A simulator in
the loop"): a prediction that starts from the latest flow and holds it, carried frame by frame
with the source re-injected, beat every physical term tried there (buoyancy fitted or fixed,
the velocity's own advection, the projection: the reconstructions gain 2-3 % of their mass a
frame, which an incompressible flow cannot carry); the physical simulator (``incompressible``,
``self_advection``, ``fit_buoyancy``, ``start="assimilated"``) is what recovers a simulated
plume's velocity (scripts/simulated_plume.py).

The simulation runs in a box around the smoke: the cells within ``margin`` of where any frame
of the window has smoke (1 % of its peak) across the up axis, the whole grid along it (smoke
rises). What it returns carries frame t on (:meth:`Assimilation.predict`): from the velocity the
simulation reached at frame t (``start="assimilated"``) or from a velocity given, the flow
fitted from frame t - 1 to t (``start="flow"``: the latest the images say), with the buoyancy
fitted, frame t's own source held.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from flamerecon.dynamics.conventions import up_of
from flamerecon.dynamics.flow import _Projected, control_spacing, gradient_energy, smoke_mask
from flamerecon.dynamics.motion import control_shape
from flamerecon.dynamics.simulation import Smoke, inflow_region, project
from flamerecon.fit.build import Setup
from flamerecon.fit.option_rules import check_section
from flamerecon.operators.warp import upsample_displacement


@dataclass(frozen=True)
class SimulationOptions:
    """The simulator in the loop (module doc): ``window`` frames fitted before the start frame,
    the initial velocity's ``control`` cells and roughness weight ``smooth``, the ``buoyancy``
    to start from (cells per frame^2 at the window's peak density) and whether it is fitted
    (``fit_buoyancy``), L-BFGS ``iters``, the source region's ``inflow`` fraction of the box
    along ``up`` (None: the scene's), the advection ``scheme``, the projection's ``pad`` of still
    cells, whether the velocity is projected at all (``incompressible``) and advected by itself
    (``self_advection``), the ``margin`` of the simulated box around the smoke, the ``outside``
    weight, where a prediction starts (``start``; ``flow``: the flow of the last frame pair;
    ``assimilated``: the simulation's velocity at the window's end), ``frame_rate`` (None: the
    scene's)."""

    window: int = 4
    control: int = 16
    smooth: float = 30.0
    buoyancy: float = 0.0
    fit_buoyancy: bool = False
    iters: int = 20
    inflow: float = 0.12
    scheme: str = "semi_lagrangian"
    pad: int = 8
    margin: int = 6
    outside: float = 1.0
    incompressible: bool = False
    self_advection: bool = False
    start: str = "flow"
    up: str | None = None
    frame_rate: float | None = None

    def __post_init__(self) -> None:
        check_section("simulation", self)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def simulation_box(densities: Sequence[torch.Tensor], up: str, margin: int) -> tuple[slice, slice, slice]:
    """The (k, j, i) slices of the simulated box: where any density (C, nz, ny, nx) has smoke,
    ``margin`` cells around, across ``up``; the whole grid along it."""
    shape = tuple(int(n) for n in densities[0].shape[1:])
    smoke = torch.zeros(shape, dtype=torch.bool, device=densities[0].device)
    for x in densities:
        smoke |= smoke_mask(x)
    axis = 2 - "xyz".index(up[-1])
    if not bool(smoke.any()):
        return tuple(slice(0, n) for n in shape)  # type: ignore[return-value]
    kji = smoke.nonzero()
    lo = (kji.amin(0) - margin).clamp_min(0).tolist()
    hi = [min(int(h) + margin + 1, n) for h, n in zip(kji.amax(0).tolist(), shape)]
    lo[axis], hi[axis] = 0, shape[axis]
    return tuple(slice(a, b) for a, b in zip(lo, hi))  # type: ignore[return-value]


class _Frame:
    """What the loss reads of one frame's setup inside the simulated box: its pixels, which
    rows of its hull lie in the box (``rows``) and where they are in the box (``cells``), the
    box's cells off its hull (``off``), and the scale r0 of its unmoved residual."""

    def __init__(self, setup: Setup, box: tuple[slice, slice, slice], previous: torch.Tensor) -> None:
        shape = tuple(setup.grid.shape)
        device = setup.voxel_index.device
        k, j, i = (torch.arange(shape[a], device=device)[box[a]] for a in range(3))
        sub = (k[:, None, None] * shape[1] + j[None, :, None]) * shape[2] + i[None, None, :]  # (bz, by, bx) flat
        lookup = torch.full((math.prod(shape),), -1, dtype=torch.long, device=device)
        lookup[setup.voxel_index.long()] = torch.arange(setup.voxel_index.numel(), device=device)
        row = lookup[sub.reshape(-1)]
        self.cells = (row >= 0).nonzero().squeeze(1)
        self.rows = row[self.cells]
        self.off = (row < 0).nonzero().squeeze(1)
        self.setup = setup
        self.m = int(setup.voxel_index.numel())
        self.b = setup.pixels.to(torch.float64)
        self.b_norm = float(self.b.pow(2).sum().clamp_min(1e-300))
        with torch.no_grad():
            self.r0 = max(float(self.residual(previous[(slice(None), *box)].double()).pow(2).sum()) / self.b_norm,
                          1e-12)

    def residual(self, x: torch.Tensor) -> torch.Tensor:
        """A x - b (N, C) of a density ``x`` (C, bz, by, bx) on the simulated box."""
        flat = x.reshape(x.shape[0], -1)
        y = flat.new_zeros(self.m, x.shape[0]).index_copy(0, self.rows, flat[:, self.cells].T)
        return _Projected.apply(y, self.setup.operator, self.setup.pixels.dtype) - self.b

    def loss(self, x: torch.Tensor, outside: float, norm: float) -> torch.Tensor:
        r = 0.5 * self.residual(x).pow(2).sum() / self.b_norm
        if outside and self.off.numel():
            r = r + outside * 0.5 * x.reshape(x.shape[0], -1)[:, self.off].pow(2).sum() / norm
        return r / self.r0


@dataclass
class Assimilation:
    """A simulation fitted to a window (module doc): the ``box`` it runs in, the velocity
    ``u`` (3, bz, by, bx) it reached at the window's last frame (cells per frame), the
    ``buoyancy`` (cells per frame^2 at density ``peak``), the source ``region`` and ``source``
    density (C, bz, by, bx) of the last frame, the ``up`` axis, the options and the record:
    each frame's relative residual before (``r0``) and after, seconds."""

    box: tuple[slice, slice, slice]
    shape: tuple[int, int, int]
    u: torch.Tensor
    buoyancy: float
    peak: float
    region: torch.Tensor
    source: torch.Tensor
    up: str
    options: SimulationOptions
    control: torch.Tensor
    record: dict = field(default_factory=dict)

    def smoke(self) -> Smoke:
        o = self.options
        return Smoke(tuple(self.u.shape[1:]), self.up, self.buoyancy, self.peak, self.region, o.scheme, o.pad,
                     o.incompressible, o.self_advection)

    def predict(self, density: torch.Tensor, steps: int, velocity: torch.Tensor | None = None
                ) -> Iterator[torch.Tensor]:
        """``density`` (C, nz, ny, nx), the window's last frame, carried 1, 2, ... ``steps``
        frames on (each yielded on the whole grid, zero outside the box), the source held; from
        ``velocity`` (3, nz, ny, nx), cells per frame, where ``options.start`` is ``flow`` and one
        is given (projected where incompressible), else from :attr:`u`."""
        x = density.detach().to(self.u)[(slice(None), *self.box)]
        u = self.u
        if velocity is not None and self.options.start == "flow":
            u = velocity.detach().to(self.u)[(slice(None), *self.box)]
            u = project(u, int(self.options.pad)) if self.options.incompressible else u
        full = torch.zeros(density.shape, dtype=self.u.dtype, device=self.u.device)
        with torch.no_grad():
            for x_n, _ in self.smoke().run(x, u, steps, lambda n: self.source):
                out = full.clone()
                out[(slice(None), *self.box)] = x_n
                yield out.to(density.dtype)

    def velocity(self) -> torch.Tensor:
        """The velocity at the window's last frame on the whole grid (3, nz, ny, nx), zero
        outside the box, cells per frame."""
        out = torch.zeros(3, *self.shape, dtype=self.u.dtype, device=self.u.device)
        out[(slice(None), *self.box)] = self.u
        return out


def assimilate(densities: Sequence[torch.Tensor], setups: Sequence[Setup], options: SimulationOptions | None = None,
               init: torch.Tensor | None = None) -> Assimilation:
    """The simulation of frames t - W .. t fitted to their images (module doc): ``densities``
    the W + 1 reconstructions (C, nz, ny, nx) of those frames, ``setups`` the W setups of frames
    t - W + 1 .. t (their operators and training pixels); ``init``: a velocity or control grid
    (3, ...) in cells per frame to start from (e.g. the flow of frames t - W -> t - W + 1)."""
    options = options or SimulationOptions()
    started = time.perf_counter()
    if len(setups) != len(densities) - 1 or not setups:
        raise ValueError(f"assimilate: {len(densities)} densities need {len(densities) - 1} setups, got {len(setups)}")
    device = setups[0].voxel_index.device
    up = up_of(setups[-1].scene, options.up)
    xs = [d.detach().to(device, torch.float64) for d in densities]
    box = simulation_box(xs, up, int(options.margin))
    crop = [x[(slice(None), *box)] for x in xs]
    shape = tuple(int(n) for n in crop[0].shape[1:])
    regions = [inflow_region(x, up, float(options.inflow)) for x in crop]
    frames = [_Frame(s, box, xs[n]) for n, s in enumerate(setups)]
    peak = float(torch.stack([x.sum(0).max() for x in crop]).max().clamp_min(1e-30))
    norm = float(crop[0].pow(2).sum().clamp_min(1e-300))
    cshape = control_shape(shape, int(options.control))
    if init is None:
        control = torch.zeros(3, *cshape, dtype=torch.float64, device=device)
    else:
        start = init.detach().to(device, torch.float64)
        if tuple(start.shape[1:]) == tuple(xs[0].shape[1:]):
            start = start[(slice(None), *box)]
        control = F.interpolate(start[None], size=cshape, mode="trilinear", align_corners=True)[0]
    control = control.clone().requires_grad_(True)
    b = torch.tensor(float(options.buoyancy), dtype=torch.float64, device=device, requires_grad=options.fit_buoyancy)
    spacing = control_spacing(shape, control)
    params = [control, b] if options.fit_buoyancy else [control]
    region = regions[-1]

    def simulate(c: torch.Tensor, buoyancy: torch.Tensor) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        smoke = Smoke(shape, up, buoyancy, peak, region, options.scheme, int(options.pad), options.incompressible,
                      options.self_advection)
        u0 = upsample_displacement(c, shape)
        if options.incompressible:
            u0 = project(u0, int(options.pad))
        return smoke.run(crop[0], u0, len(frames), lambda n: crop[n])

    def objective(c: torch.Tensor, buoyancy: torch.Tensor) -> tuple[torch.Tensor, list[float]]:
        loss, parts = 0.0, []
        for frame, (x, _) in zip(frames, simulate(c, buoyancy)):
            term = frame.loss(x, float(options.outside), norm)
            parts.append(float(term.detach()) * frame.r0)
            loss = loss + term / len(frames)
        return loss + float(options.smooth) * gradient_energy(c, spacing), parts

    with torch.no_grad():
        _, before = objective(control, b)
    fitted = options.fit_buoyancy or options.start == "assimilated"  # else no prediction reads the fit
    if fitted:
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=int(options.iters), history_size=10,
                                line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss, _ = objective(control, b)
            loss.backward()
            return loss

        opt.step(closure)
    control, buoyancy = control.detach(), float(b.detach())
    with torch.no_grad():
        _, after = objective(control, b.detach())
        u = None
        for _, u in simulate(control, b.detach()):
            pass
    record = {"frames": len(frames), "fitted": fitted, "buoyancy_cells_per_frame2": buoyancy, "box": [[s.start, s.stop] for s in box],
              "residual_unmoved": [f.r0 for f in frames], "residual_start": before, "residual": after,
              "mean_speed_cells": float(u[:, smoke_mask(crop[-1])].norm(dim=0).mean()),
              "seconds": time.perf_counter() - started}
    return Assimilation(box, tuple(int(n) for n in xs[0].shape[1:]), u, buoyancy, peak, region, crop[-1] * region,
                        up, options, control, record)
