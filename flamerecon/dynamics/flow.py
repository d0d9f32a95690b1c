"""Flow from a reconstructed sequence: a velocity per frame pair, fitted to the next frame's
images through its projector, smooth and nearly divergence-free, and the predictions it makes.

Frame t's density x_t (C, nz, ny, nx) and the velocity u_t (3, nz, ny, nx), cells per frame,
components (x, y, z), carry the smoke onto frame t+1 by one semi-Lagrangian step,
(W_u x)(p) = x(p - u(p)) (:func:`~flamerecon.operators.warp.warp_volume`). u_t minimises

    [0.5 ||A_{t+1} W_u x_t - b_{t+1}||^2 / ||b_{t+1}||^2         frame t+1's images (its hull's rows)
     + outside * 0.5 ||W_u x_t off hull_{t+1}||^2 / ||x_t||^2] / r0   smoke carried where t+1's cameras see none
  + smooth * R(u) + divergence * mean(div u ^ 2 over the smoke above the inflow)

with r0 the relative image residual of x_t not moved (||A_{t+1} x_t - b_{t+1}||^2 / ||b_{t+1}||^2), so that
the weights are relative to how much the motion explains, whatever the noise and the speed,
A_{t+1}, b_{t+1} frame t+1's operator and training pixels (:class:`~flamerecon.fit.build.Setup`):
the data are the next frame's *images*, not its reconstructed density, whose unseen structure
is a guess. u lives on a coarse control grid (``control`` cells along the grid's longest side,
trilinear in between; R the mean squared velocity gradient between neighbouring control points,
1/frame^2, so that a weight means the same on any grid and control grid), fitted
coarse to fine (``control``/4, /2, then ``control`` cells, the density blurred by 2, 1, 0 cells)
by L-BFGS, every term evaluated only on the cells that can hold smoke (t+1's hull and t's smoke
dilated by ``margin`` cells). The divergence (central differences of one cell, 1/frame) is
penalised where the smoke is (1 % of frame t's peak), but not in the ``inflow`` region, the
bottom fraction of the box along ``up``, where the source injects smoke: there the velocity is
free to diverge, and a backward warp whose speed grows upwards out of the source stretches the smoke into new smoke. Along a
sequence each pair starts from the previous pair's velocity and fits only the finest grid
(``warm_iters`` iterations).

:func:`advect` carries a density k frames ahead along a steady velocity
(:func:`~flamerecon.operators.warp.advect_volume`). :func:`shift_residuals` scores uniform
vertical shifts on the same data term, the baseline a fitted flow must beat.

Chosen on ScalarFlow frames 30-39 (predictions up to frame 49, train02 held out;
docs/results.md, "Flow"): 16 control cells (24 fits the next frame better, 16 predicts 10 frames
ahead better), smooth 30 (10-300 within 0.1 dB held out at k <= 5; 30 best on the training views),
divergence 30 (the relative divergence 0.46 -> 0.15, for 0.1-0.5 dB of held-out PSNR at k = 1-5:
the price of an incompressible flow on this capture), inflow 0.12 (0.06-0.2 alike), warm starts
of 15 iterations (as good as 3 x 30 cold ones, 4-6 x faster).

    import flamerecon as fr
    recs = [fr.reconstruct(fr.load_scene("scalarflow", frame=t), fr.preset("scalarflow")) for t in (40, 41, 42)]
    flow = fr.estimate_flow(recs)                    # two velocities: 40 -> 41, 41 -> 42
    flow.velocity(0, "world")                        # (3, nz, ny, nx) in m/s
    fr.advect(recs[0].density, flow.pairs[0].u, 5)   # frame 40 carried 5 frames ahead
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from flamerecon.arguments import fields, instance, tensor, value, wrong_value
from flamerecon.dynamics.conventions import heights, up_of
from flamerecon.dynamics.motion import _blur, control_shape
from flamerecon.fit.build import Setup
from flamerecon.fit.option_rules import check_fields, check_section
from flamerecon.geometry.axes import up_vector
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.base import LinearOperator
from flamerecon.operators.warp import (
    advect_volume,
    cell_points,
    curl,
    divergence,
    sample_points,
    upsample_displacement,
)
from flamerecon.progress import Progress
from flamerecon.rules import integer


@dataclass(frozen=True)
class FlowOptions:
    """How a velocity is fitted (module doc): ``control`` cells of its finest control grid
    along the grid's longest side; weights ``smooth`` (roughness), ``divergence`` (div u
    squared, 0: off) and ``outside`` (smoke carried off the next frame's hull); ``inflow``, the
    bottom fraction of the box along ``up`` where the divergence is free; ``iters`` L-BFGS
    iterations per control grid from cold, ``warm_iters`` on the finest grid when
    ``warm_start`` starts a pair from the previous one; ``margin`` cells around the smoke where
    the fit looks; ``up`` the axis the inflow region is at the bottom of (None: the scene's,
    :func:`~flamerecon.dynamics.conventions.up_of`); ``frame_rate`` (frames per second) to give
    velocities in world units per second (None: the capture's, where its files say)."""

    control: int = 16
    smooth: float = 30.0
    divergence: float = 30.0
    inflow: float = 0.12
    outside: float = 1.0
    iters: int = 30
    warm_iters: int = 15
    warm_start: bool = True
    margin: int = 4
    up: str | None = None
    frame_rate: float | None = None

    def __post_init__(self) -> None:
        check_section("flow", self)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def control_spacing(shape: tuple[int, int, int], control: torch.Tensor) -> tuple[float, float, float]:
    """(x, y, z) spacing of a corner-aligned control grid (3, gz, gy, gx) in cells of ``shape``."""
    nz, ny, nx = shape
    gz, gy, gx = control.shape[1:]
    return tuple((n - 1) / max(g - 1, 1) for n, g in ((nx, gx), (ny, gy), (nz, gz)))  # type: ignore[return-value]


class _Projected(torch.autograd.Function):
    """y (M, C) -> A y (N, C) with the adjoint as its gradient: the projector inside autograd."""

    @staticmethod
    def forward(ctx, y: torch.Tensor, A: LinearOperator, dtype: torch.dtype) -> torch.Tensor:
        ctx.A, ctx.dtype = A, y.dtype
        return A.forward(y.to(dtype).contiguous()).to(y.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return ctx.A.adjoint(grad.to(torch.float32).contiguous()).to(ctx.dtype), None, None


def gradient_energy(control: torch.Tensor, spacing: tuple[float, float, float]) -> torch.Tensor:
    """R(u): the mean squared difference of neighbouring control points along each axis, each
    divided by their distance in cells (``spacing`` (x, y, z)): the squared velocity gradient,
    1/frame^2, whatever the control grid's and the grid's resolution."""
    terms = [(control.diff(dim=3 - a) / spacing[a]).pow(2).mean() for a in range(3) if control.shape[3 - a] > 1]
    return sum(terms) if terms else control.sum() * 0


def divergence_probes(points: torch.Tensor) -> torch.Tensor:
    """(3, 2, 3, P): ``points`` (3, P) moved one cell forward and back along x, y and z in
    turn, where :func:`probed_divergence` reads each velocity component."""
    step = torch.eye(3, dtype=points.dtype, device=points.device)[:, :, None]  # (axis, xyz, 1)
    return torch.stack([points + step, points - step], 1)


def probed_divergence(control: torch.Tensor, probes: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(P,): div u at the cells probed (:func:`divergence_probes`) of the velocity a control
    grid (3, gz, gy, gx) interpolates, central differences of one cell (1/frame); ``scale``
    (3, 1) takes cells to control coordinates."""
    total = 0
    for a in range(3):
        ahead, behind = sample_points(control[a:a + 1], probes[a].permute(1, 0, 2).reshape(3, -1) * scale,
                                      "border").reshape(2, -1)
        total = total + 0.5 * (ahead - behind)
    return total


@dataclass
class PairFlow:
    """The velocity from one frame to the next: ``u`` (3, nz, ny, nx) in cells per frame
    (components x, y, z) and its ``control`` grid; the data term's relative residual
    ||A W x - b||^2 / ||b||^2 with u = 0 (``residual_none``) and fitted (``residual``); the
    divergence's RMS over the smoke above the inflow relative to the RMS of the velocity
    gradient there (``relative_divergence``; 0: divergence-free); the mean speed in the smoke
    (cells per frame); ``seconds`` of the fit and whether it was warm-started."""

    u: torch.Tensor
    control: torch.Tensor
    residual_none: float
    residual: float
    relative_divergence: float
    mean_speed: float
    seconds: float
    warm: bool
    frame: int | None = None

    def record(self) -> dict:
        """The numbers of the fit (no tensors), for metrics files and TensorBoard."""
        return {"frame": self.frame, "residual_none": self.residual_none, "residual": self.residual,
                "relative_divergence": self.relative_divergence, "mean_speed_cells": self.mean_speed,
                "seconds": self.seconds, "warm": self.warm}


def smoke_mask(density: torch.Tensor, level: float = 0.01) -> torch.Tensor:
    """(nz, ny, nx) bool: where the channel sum of ``density`` exceeds ``level`` times its peak."""
    total = density.detach().sum(0)
    return total > level * float(total.max().clamp_min(1e-30))


def flow_statistics(u: torch.Tensor, density: torch.Tensor, options: FlowOptions, up: str) -> tuple[float, float]:
    """(relative divergence, mean speed in cells per frame) of ``u`` (3, nz, ny, nx) over the
    smoke of ``density`` above the inflow region (see :class:`PairFlow`); NaN without smoke."""
    mask = smoke_mask(density) & (heights(tuple(u.shape[1:]), up, u.dtype) >= options.inflow).to(u.device)
    if not bool(mask.any()):
        return math.nan, math.nan
    lo, hi = _box(mask.nonzero().T, 2, tuple(u.shape[1:]))
    u, mask = u[(slice(None), *lo_hi(lo, hi))], mask[lo_hi(lo, hi)]  # the smoke's box, a cell around
    div = divergence(u)
    gradient = torch.stack([torch.gradient(u[c], dim=d)[0] for c in range(3) for d in range(3) if u.shape[1 + d] > 1])
    rms_div = float(div[mask].pow(2).mean().sqrt())
    rms_grad = float(gradient[:, mask].pow(2).sum(0).mean().sqrt())
    speed = float(u[:, mask].norm(dim=0).mean())
    return (rms_div / rms_grad if rms_grad > 0 else 0.0), speed


def _box(kji: torch.Tensor, pad: int, shape: tuple[int, int, int]) -> tuple[list[int], list[int]]:
    """[lo, hi) (k, j, i) of the cells ``kji`` (3, P), ``pad`` cells around, inside ``shape``."""
    lo = (kji.amin(1) - pad).clamp_min(0).tolist()
    hi = [min(int(h) + pad + 1, n) for h, n in zip(kji.amax(1).tolist(), shape)]
    return lo, hi


def lo_hi(lo: list[int], hi: list[int]) -> tuple[slice, slice, slice]:
    return tuple(slice(a, b) for a, b in zip(lo, hi))  # type: ignore[return-value]


class _PairData:
    """What a pair's fit reads: frame t's density cropped around where it can move (``x``,
    float64, its cell (0, 0, 0) at ``offset`` (x, y, z) of the grid), the cells ``points``
    (3, P) where the moved density is read, the first ``inside`` of them frame t+1's hull in
    its operator's column order, the others the smoke's surroundings off that hull."""

    def __init__(self, source: torch.Tensor, target: Setup, margin: int, pad: int) -> None:
        shape = tuple(target.grid.shape)
        device = target.voxel_index.device
        x = source.detach().to(device, torch.float64)
        support = x.abs().sum(0) > 0
        kji = support.nonzero().T
        lo, hi = _box(kji if kji.numel() else torch.zeros(3, 1, dtype=torch.long), pad + margin, shape)
        box = lo_hi(lo, hi)
        near = torch.zeros(shape, dtype=torch.bool, device=device)
        near[box] = _dilate(support[box], margin)
        extra = (near & ~target.hull.to(device)).reshape(-1).nonzero().squeeze(1)
        self.inside = int(target.voxel_index.numel())
        self.points = cell_points(torch.cat([target.voxel_index.to(device), extra]), shape)
        self.x = x[(slice(None), *box)]
        self.offset = torch.tensor(lo[::-1], dtype=torch.float64, device=device)[:, None]
        self.norm = float(x.pow(2).sum().clamp_min(1e-300))
        self.target = target
        self.b = target.pixels.to(torch.float64)
        self.b_norm = float(self.b.pow(2).sum().clamp_min(1e-300))

    def moved(self, volume: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """(C, P): ``volume`` (cropped as :attr:`x`) carried by ``u`` (3, P) read at the points."""
        return sample_points(volume, self.points - u - self.offset)

    def residual(self, moved: torch.Tensor) -> torch.Tensor:
        """A W_u x - b (N, C) of the moved density (C, P), differentiable."""
        return _Projected.apply(moved[:, :self.inside].T, self.target.operator, self.target.pixels.dtype) - self.b

    def relative_residual(self, u: torch.Tensor) -> float:
        with torch.no_grad():
            return float(self.residual(self.moved(self.x, u)).pow(2).sum()) / self.b_norm


def _dilate(mask: torch.Tensor, cells: int) -> torch.Tensor:
    """A (nz, ny, nx) bool mask grown by ``cells`` along each axis in turn (a box of 2 cells + 1)."""
    grown = mask.float()[None, None]
    for axis in range(3):
        kernel = [1, 1, 1]
        kernel[axis] = 2 * cells + 1
        padding = [0, 0, 0]
        padding[axis] = cells
        grown = F.max_pool3d(grown, tuple(kernel), 1, tuple(padding))
    return grown[0, 0] > 0


def relative_residual(source: torch.Tensor, target: Setup, u: torch.Tensor | None) -> float:
    """||A W_u x - b||^2 / ||b||^2 of density ``source`` (C, nz, ny, nx) carried one frame by
    ``u`` (3, nz, ny, nx) in cells per frame (None: not moved) into the images of ``target``."""
    data = _PairData(source, target, 1, 1)
    if u is None:
        return data.relative_residual(torch.zeros_like(data.points))
    return data.relative_residual(sample_points(u.to(data.points), data.points, "border"))


def estimate_velocity(source: torch.Tensor, target: Setup, options: FlowOptions | None = None,
                      init: torch.Tensor | None = None, frame: int | None = None) -> PairFlow:
    """The velocity carrying density ``source`` (C, nz, ny, nx) on ``target``'s grid into the
    images of ``target`` (the next frame's :class:`~flamerecon.fit.build.Setup`), module doc;
    ``init``: a control grid (3, gz, gy, gx) to start from (a warm start: only the finest
    grid is fitted, ``options.warm_iters`` iterations)."""
    instance("estimate_velocity.target", target, Setup)
    options = instance("estimate_velocity.options", options, FlowOptions, null=True) or FlowOptions()
    shape = tuple(target.grid.shape)
    source = tensor("estimate_velocity.source", source, "(C, nz, ny, nx) on the target's grid",
                    shape=(int(target.pixels.shape[1]), *shape), finite=True)
    init = tensor("estimate_velocity.init", init, "(3, gz, gy, gx) control grid", ndim=4, finite=True, null=True)
    if init is not None and init.shape[0] != 3:
        raise wrong_value("estimate_velocity.init", init, "(3, gz, gy, gx): a control grid of the three components")
    started = time.perf_counter()
    device = target.voxel_index.device
    stages = sorted({max(2, options.control // 4), max(2, options.control // 2), int(options.control)})
    data = _PairData(source, target, int(options.margin), 3 * 2 ** (len(stages) - 1))
    up = up_of(target.scene, options.up)
    smoke = smoke_mask(source) & (heights(shape, up) >= options.inflow).to(source.device)
    probes = divergence_probes(cell_points(smoke.reshape(-1).nonzero().squeeze(1).to(device), shape))
    unmoved = max(data.relative_residual(torch.zeros_like(data.points)), 1e-12)  # the data terms' scale

    def fit_stage(control: torch.Tensor, sigma: float, iters: int) -> torch.Tensor:
        control = control.detach().clone().requires_grad_(True)
        blurred = _blur(data.x, sigma)
        scale = _to_control(shape, control)
        spacing = control_spacing(shape, control)
        opt = torch.optim.LBFGS([control], lr=1.0, max_iter=int(iters), history_size=10,
                                line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            moved = data.moved(blurred, sample_points(control, data.points * scale, "border"))
            loss = 0.5 * data.residual(moved).pow(2).sum() / data.b_norm
            if options.outside and moved.shape[1] > data.inside:
                loss = loss + float(options.outside) * 0.5 * moved[:, data.inside:].pow(2).sum() / data.norm
            loss = loss / unmoved + float(options.smooth) * gradient_energy(control, spacing)
            if options.divergence and probes.shape[1]:
                loss = loss + float(options.divergence) * probed_divergence(control, probes, scale).pow(2).mean()
            loss.backward()
            return loss

        opt.step(closure)
        return control.detach()

    finest = control_shape(shape, int(options.control))
    warm = init is not None
    if warm:
        control = F.interpolate(init.to(device, torch.float64)[None], size=finest, mode="trilinear",
                                align_corners=True)[0]
        control = fit_stage(control, 0.0, options.warm_iters)
    else:
        control = torch.zeros(3, *control_shape(shape, stages[0]), dtype=torch.float64, device=device)
        for level, cells in enumerate(stages):
            control = F.interpolate(control[None], size=control_shape(shape, cells), mode="trilinear",
                                    align_corners=True)[0]
            control = fit_stage(control, float(2 ** (len(stages) - 1 - level)) if level < len(stages) - 1 else 0.0,
                                options.iters)
    seconds = time.perf_counter() - started
    u = upsample_displacement(control, shape)
    rel_div, speed = flow_statistics(u, source.to(device), options, up)
    at_points = sample_points(control, data.points * _to_control(shape, control), "border")
    return PairFlow(u.float(), control.float(), unmoved, data.relative_residual(at_points), rel_div, speed,
                    seconds, warm, frame)


def _to_control(shape: tuple[int, int, int], control: torch.Tensor) -> torch.Tensor:
    """(3, 1): factors taking cell coordinates (x, y, z) of ``shape`` to the control grid's."""
    nz, ny, nx = shape
    gz, gy, gx = control.shape[1:]
    return torch.tensor([(g - 1) / max(n - 1, 1) for n, g in ((nx, gx), (ny, gy), (nz, gz))],
                        dtype=control.dtype, device=control.device)[:, None]


@dataclass
class Flow:
    """Velocities of a sequence: ``pairs[i]`` carries frame ``frames[i]`` onto the next, on
    ``grid``; ``frame_rate`` (frames per second, None: unknown) converts cells per frame to
    world units per second."""

    grid: VoxelGrid
    frames: list[int]
    pairs: list[PairFlow]
    options: FlowOptions
    frame_rate: float | None = None
    seconds: float = 0.0
    records: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        fields(self)
        if len(self.frames) != len(self.pairs):
            raise wrong_value("Flow.frames", self.frames, f"one frame number per pair ({len(self.pairs)})")
        for i, pair in enumerate(self.pairs):
            tensor(f"Flow.pairs[{i}].u", pair.u, "(3, nz, ny, nx) on the grid", shape=(3, *self.grid.shape))

    def velocity(self, index: int, units: str = "cells") -> torch.Tensor:
        """Pair ``index``'s velocity (3, nz, ny, nx): ``cells`` per frame, or ``world`` units
        (the scene's: metres for ScalarFlow) per second."""
        value("Flow.velocity.index", index, integer(0, len(self.pairs) - 1))
        if units not in ("cells", "world"):
            raise wrong_value("Flow.velocity.units", units, "'cells' (per frame) or 'world' (units per second)")
        u = self.pairs[index].u
        return u if units == "cells" else cells_to_world(u, self.grid, self.frame_rate)

    def predict(self, density: torch.Tensor, index: int, steps: int) -> torch.Tensor:
        """``density`` (C, nz, ny, nx) carried ``steps`` frames by pair ``index``'s velocity."""
        value("Flow.predict.index", index, integer(0, len(self.pairs) - 1))
        return advect(density, self.pairs[index].u, steps)


def cells_to_world(u: torch.Tensor, grid: VoxelGrid, frame_rate: float | None) -> torch.Tensor:
    """A velocity (3, ...) in cells per frame as world units per second on ``grid``."""
    if frame_rate is None:
        raise wrong_value("frame_rate", frame_rate, "a number of frames per second (flow.frame_rate): the "
                          "scene does not say its frame rate")
    size = grid.voxel_size(u.device).to(u.dtype)
    return u * size.reshape(3, *[1] * (u.ndim - 1)) * float(frame_rate)


def advect(density: torch.Tensor, u: torch.Tensor, steps: int) -> torch.Tensor:
    """``density`` (C, nz, ny, nx) carried ``steps`` >= 0 frames (at most
    :data:`~flamerecon.fit.option_rules.MAX_STEPS`) along the steady velocity
    ``u`` (3, nz, ny, nx), cells per frame (:func:`~flamerecon.operators.warp.advect_volume`)."""
    density = tensor("advect.density", density, "(C, nz, ny, nx)", ndim=4, finite=True)
    u = tensor("advect.velocity", u, "(3, nz, ny, nx) in cells per frame", shape=(3, *density.shape[1:]),
               finite=True)
    check_fields("advect", {"steps": steps})  # an integer >= 0, at most MAX_STEPS frames
    return advect_volume(density, u.to(density.device, density.dtype), int(steps))


def uniform_velocity(shape: tuple[int, int, int], speed: float, up: str = "+y", device=None) -> torch.Tensor:
    """(3, nz, ny, nx): ``speed`` cells per frame along ``up`` everywhere."""
    direction = torch.tensor(up_vector(up), dtype=torch.float32, device=device) * float(speed)
    return direction.reshape(3, 1, 1, 1).expand(3, *shape).contiguous()


def shift_residuals(source: torch.Tensor, target: Setup, speeds: Sequence[float], up: str = "+y") -> list[float]:
    """||A S_v x - b||^2 / ||b||^2 for each uniform shift S_v of ``speeds`` cells per frame
    along ``up``: the data term of the baseline a fitted flow is compared with."""
    shape = tuple(target.grid.shape)
    return [relative_residual(source, target, uniform_velocity(shape, v, up, source.device)) for v in speeds]


def vorticity(u: torch.Tensor) -> torch.Tensor:
    """curl u (3, nz, ny, nx) of a velocity in cells per frame: radians per frame."""
    return curl(u)


def estimate_flow(densities: Sequence[torch.Tensor], next_setup: Callable[[int], Setup], grid: VoxelGrid,
                  options: FlowOptions | None = None, frames: Sequence[int] | None = None,
                  frame_rate: float | None = None) -> Flow:
    """The velocity of every consecutive pair of ``densities`` (C, nz, ny, nx) on ``grid``:
    pair i is fitted to the images of ``next_setup(i + 1)`` (frame i + 1's setup, asked for once
    each, in order, so that a caller can build them one at a time) and, with
    ``options.warm_start``, started from pair i - 1's velocity. Progress is logged per pair."""
    options = options or FlowOptions()
    started = time.perf_counter()
    frames = list(range(len(densities))) if frames is None else list(frames)
    progress = Progress("flow", len(densities) - 1, "frame pair")
    pairs: list[PairFlow] = []
    for i in range(len(densities) - 1):
        init = pairs[-1].control if options.warm_start and pairs else None
        pair = estimate_velocity(densities[i], next_setup(i + 1), options, init, frames[i])
        pairs.append(pair)
        progress.update(i + 1, f"frame {frames[i]}: residual {pair.residual_none:.4f} -> {pair.residual:.4f}")
    return Flow(grid, frames[:-1], pairs, options, frame_rate, time.perf_counter() - started,
                [p.record() for p in pairs])
