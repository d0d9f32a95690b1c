"""Detail from time: frame t reconstructed with its neighbours' views, carried onto it by their
motion.

Consecutive frames are the same smoke moved a little, seen again by the same cameras. With a
displacement u_s from frame t to each frame s of a window around t (:func:`estimate_displacement`,
a smooth field on a coarse control grid, coarse to fine), frame t's density x solves the
shared-density problem

    min_x  sum_{s in window} w_s 0.5||A_s W_{u_s} x - b_s||^2 + l1 sum(x) + mu TV(x),  x >= 0,

with w_t = 1, w_s = ``decay`` ** |s - t| and W_u the trilinear backward warp of
:mod:`flamerecon.operators.warp` from frame t's hull onto frame s's: the neighbours' cameras
become extra views of frame t's structure. It is the ``tv`` (or ``fista``) solve of the stacked
operator [sqrt(w_s) A_s W_{u_s}], with ``solver.l1_rel`` and ``solver.tv`` relative to that
operator's max(A^T b) (which grows with the data as the data term does), warm-started from
frame t's own solution, then debiased on the stacked rows as ``options.debias`` says.

The displacement is fitted to the per-frame solutions (``fit_to="density"``: min_u
||x_s - W_u x_t||^2 / ||x_s||^2 + smooth * R(u)) or to the neighbour's images through its
projector (``fit_to="images"``: min_u ||A_s W_u x_t - b_s||^2 / ||b_s||^2 + smooth * R(u), which
does not trust x_s's own 3D structure), R the mean squared difference of neighbouring control
points (cells^2), from the best whole-cell shift, by L-BFGS through ``grid_sample``.

    import flamerecon as fr
    scenes = [fr.load_scene("scalarflow", frame=t) for t in (38, 39, 40, 41, 42)]
    rec = fr.reconstruct_motion(scenes, fr.preset("scalarflow"), fr.MotionOptions(window=5))
    rec.density, rec.score()                           # frame 40, with 4 neighbours' views
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from flamerecon.arguments import fields, instance, wrong_value
from flamerecon.device import resolve_device, set_threads
from flamerecon.errors import ConfigError
from flamerecon.evaluate.result_warnings import penalty_of, result_warnings
from flamerecon.evaluate.scores import score
from flamerecon.fit.build import Setup, build, check_frame_inputs
from flamerecon.fit.debias import debias
from flamerecon.fit.option_rules import check_section
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import Fit, calibrated_scene, fit
from flamerecon.operators.warp import (
    ComposedOperator,
    RowStack,
    upsample_displacement,
    warp_matrix,
    warp_volume,
)
from flamerecon.scenes import Scene
from flamerecon.solvers import Problem, lambda_max, make_solver
from flamerecon.solvers.temporal import estimate_shift

MOTION_SOLVERS = ("tv", "fista")


@dataclass(frozen=True)
class MotionOptions:
    """The ``motion:`` options (module doc): ``window`` frames centred on the target (odd; 1:
    off, the single-frame reconstruction), neighbour weight ``decay`` ** |s - t|, the
    displacement's control grid (``control`` cells along the grid's longest side, fitted
    through coarser ones first), its smoothness weight ``smooth``, L-BFGS ``iters`` per stage,
    the whole-cell shift search of its start (``max_shift`` cells) and ``fit_to``: density or
    images."""

    window: int = 1
    decay: float = 0.5
    control: int = 8
    smooth: float = 0.01
    iters: int = 30
    max_shift: int = 4
    fit_to: str = "density"

    def __post_init__(self) -> None:
        check_section("motion", self)
        if self.window % 2 != 1:
            raise wrong_value("motion.window", self.window, "an odd number of frames (1, 3, 5, ...)")


def control_shape(shape: tuple[int, int, int], cells: int) -> tuple[int, int, int]:
    """A control grid of ``cells`` along the longest axis of ``shape`` (nz, ny, nx), the others
    in proportion, at least 2 each."""
    top = max(shape)
    return tuple(max(2, round(cells * n / top)) for n in shape)  # type: ignore[return-value]


def _blur(volume: torch.Tensor, sigma: float) -> torch.Tensor:
    """A separable Gaussian blur of (C, nz, ny, nx) by ``sigma`` cells (0: unchanged)."""
    if sigma <= 0:
        return volume
    r = int(3 * sigma + 0.5)
    t = torch.arange(-r, r + 1, dtype=volume.dtype, device=volume.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    v = volume[None]
    for axis in range(3):
        shape = [1, 1, 1, 1, 1]
        shape[2 + axis] = k.numel()
        pad = [0] * 6
        pad[2 * (2 - axis)] = pad[2 * (2 - axis) + 1] = r
        v = torch.nn.functional.conv3d(torch.nn.functional.pad(v.reshape(-1, 1, *v.shape[2:]), pad),
                                       k.reshape(shape)).reshape(v.shape)
    return v[0]


def roughness(control: torch.Tensor) -> torch.Tensor:
    """R(u): the mean squared difference of neighbouring control points, over the three axes."""
    terms = [control.diff(dim=d) for d in (1, 2, 3) if control.shape[d] > 1]
    return sum(t.pow(2).mean() for t in terms) if terms else control.sum() * 0


@dataclass
class Displacement:
    """A fitted displacement ``u`` (3, nz, ny, nx) in cells (module doc of
    :mod:`flamerecon.operators.warp`), its ``control`` grid and the relative residuals of the
    fit's data term: none (u = 0), the whole-cell ``shift`` it started from, and the fit."""

    u: torch.Tensor
    control: torch.Tensor
    shift: tuple[int, int, int]
    residual_none: float
    residual_shift: float
    residual: float

    def record(self) -> dict:
        mean = self.u.reshape(3, -1).mean(1).tolist()
        return {"shift": list(self.shift), "mean_cells": [round(v, 3) for v in mean],
                "max_cells": float(self.u.abs().max()), "residual_none": self.residual_none,
                "residual_shift": self.residual_shift, "residual": self.residual}


def estimate_displacement(source: torch.Tensor, target: torch.Tensor, motion: MotionOptions,
                          data: tuple | None = None) -> Displacement:
    """The smooth displacement u carrying density ``source`` (C, nz, ny, nx) onto ``target``
    (same shape): from the best whole-cell shift, L-BFGS over control grids of ``control`` / 4,
    / 2 and ``control`` cells (blurred by 2, 1, 0 cells), each upsampled trilinearly. ``data``:
    (A, b, voxel_index) of the target frame to fit the images instead (``fit_to="images"``)."""
    shape = tuple(int(n) for n in source.shape[1:])
    src = source.detach().double().mean(0, keepdim=True)
    tgt = target.detach().double().mean(0, keepdim=True)
    scale = float(tgt.abs().max().clamp_min(1e-12))
    src, tgt = src / scale, tgt / scale
    shift = estimate_shift(src[0], tgt[0], int(motion.max_shift))

    if data is not None:
        A, b, index = data
        b = b.detach().double()
        b_norm = float(b.pow(2).sum().clamp_min(1e-300))
        full = source.detach().double()  # every channel, in its own units

        def residual(u: torch.Tensor, blurred: torch.Tensor, _t: torch.Tensor) -> torch.Tensor:
            y = warp_volume(blurred, u).reshape(full.shape[0], -1)[:, index].T
            r = A.forward(y.detach().float()).double() - b
            if y.requires_grad:  # the data term's gradient in y, through the projector's adjoint
                y.backward(A.adjoint(r.float()).double() / b_norm, retain_graph=True)
            return (0.5 * r.pow(2).sum() / b_norm).detach()

        volumes = (full, None)
    else:
        t_norm = float(tgt.pow(2).sum().clamp_min(1e-300))

        def residual(u: torch.Tensor, blurred: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return 0.5 * (t - warp_volume(blurred, u)).pow(2).sum() / t_norm

        volumes = (src, tgt)

    def data_term(u: torch.Tensor, sigma: float) -> torch.Tensor:
        with torch.no_grad():
            s = _blur(volumes[0], sigma)
            t = None if volumes[1] is None else _blur(volumes[1], sigma)
        return residual(u, s, t)

    zero = torch.zeros(3, *shape, dtype=torch.float64, device=source.device)
    with torch.no_grad():
        none = 2 * float(data_term(zero, 0.0))
        start = torch.tensor(shift, dtype=torch.float64, device=source.device)[:, None, None, None]
        at_shift = 2 * float(data_term(zero + start, 0.0))
    control = start.expand(3, *control_shape(shape, 2)).clone()
    stages = sorted({max(2, motion.control // 4), max(2, motion.control // 2), motion.control})
    for level, cells in enumerate(stages):
        sigma = float(2 ** (len(stages) - 1 - level)) if level < len(stages) - 1 else 0.0
        control = torch.nn.functional.interpolate(control[None], size=control_shape(shape, cells),
                                                  mode="trilinear", align_corners=True)[0]
        control = control.detach().requires_grad_(True)
        with torch.no_grad():
            s_blur = _blur(volumes[0], sigma)
            t_blur = None if volumes[1] is None else _blur(volumes[1], sigma)
        opt = torch.optim.LBFGS([control], lr=1.0, max_iter=int(motion.iters), history_size=10,
                                line_search_fn="strong_wolfe")

        def closure(opt=opt, control=control, s_blur=s_blur, t_blur=t_blur) -> torch.Tensor:
            opt.zero_grad()  # (this stage's optimiser, control grid and volumes, bound here)
            u = upsample_displacement(control, shape)
            loss = float(motion.smooth) * roughness(control)
            if data is not None:
                loss.backward()
                return residual(u, s_blur, t_blur) + loss.detach()
            loss = loss + residual(u, s_blur, t_blur)
            loss.backward()
            return loss

        opt.step(closure)
    control = control.detach()
    u = upsample_displacement(control, shape)
    with torch.no_grad():
        final = 2 * float(data_term(u, 0.0))
    return Displacement(u.float(), control.float(), shift, none, at_shift, final)


@dataclass
class MotionFrame:
    """One frame of the window: its (calibrated) scene's ``setup`` and its own single-frame
    :class:`~flamerecon.fit.reconstruct.Fit`."""

    setup: Setup
    fit: Fit
    calibration: dict | None

    @property
    def density(self) -> torch.Tensor:
        return self.setup.volume(self.fit.result.x)


def prepare_window(scenes: Sequence[Scene], options: ReconstructionOptions, device: torch.device
                   ) -> list[MotionFrame]:
    """Every frame calibrated, built and fitted as :func:`~flamerecon.fit.reconstruct.reconstruct`
    would (no coarse levels, no warm start), all on one grid box."""
    frames: list[MotionFrame] = []
    for scene in scenes:
        scene, calibration = calibrated_scene(scene, options, device)
        setup = build(scene, options, device)
        first = frames[0].setup.grid if frames else setup.grid
        if (setup.grid.resolution, setup.grid.bbox_min, setup.grid.bbox_max) != (
                first.resolution, first.bbox_min, first.bbox_max):
            raise ConfigError(f"motion: frame {scene.meta.get('frame', len(frames))} has another grid box than "
                              "the first frame; set grid.bbox to one box for all frames")
        frames.append(MotionFrame(setup, fit(setup, options), calibration))
    return frames


def window_weights(offsets: Sequence[int], decay: float) -> list[float]:
    """w_s = decay ** |s - t| for frame offsets s - t."""
    return [float(decay) ** abs(int(d)) for d in offsets]


def estimate_window(frames: Sequence[MotionFrame], target: int, motion: MotionOptions) -> dict[int, Displacement]:
    """The displacement from frame ``target`` (an index of ``frames``) to each other frame."""
    source = frames[target].density
    out = {}
    for s, frame in enumerate(frames):
        if s == target:
            continue
        data = None
        if motion.fit_to == "images":
            data = (frame.setup.operator, frame.setup.pixels, frame.setup.voxel_index)
        out[s] = estimate_displacement(source, frame.density, motion, data)
    return out


def window_problem(frames: Sequence[MotionFrame], target: int, displacements: dict[int, Displacement],
                   weights: Sequence[float]) -> tuple[RowStack, torch.Tensor]:
    """The stacked operator [sqrt(w_s) A_s W_{u_s}] on frame ``target``'s hull and its data."""
    here = frames[target].setup
    blocks, data = [], []
    for s, (frame, w) in enumerate(zip(frames, weights)):
        if w <= 0:
            continue
        if s == target:
            blocks.append(ComposedOperator(here.operator, _Identity(int(here.voxel_index.numel())), w ** 0.5))
        else:
            W = warp_matrix(displacements[s].u.to(here.voxel_index.device), here.voxel_index,
                            frame.setup.voxel_index)
            blocks.append(ComposedOperator(frame.setup.operator, W, w ** 0.5))
        data.append(w ** 0.5 * frame.setup.pixels)
    return RowStack(blocks), torch.cat(data)


class _Identity:
    """The identity on M unknowns (frame t's own block)."""

    def __init__(self, m: int) -> None:
        self.shape = (m, m)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return y


@dataclass
class MotionReconstruction:
    """What :func:`reconstruct_motion` returns: frame ``target``'s density (hull values ``x``
    on ``setup``), the window's frames (their own fits: ``frames[target].fit`` is the
    single-frame reconstruction), the displacements and the record."""

    setup: Setup
    x: torch.Tensor
    frames: list[MotionFrame]
    target: int
    displacements: dict[int, Displacement]
    options: ReconstructionOptions
    record: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        fields(self)

    @property
    def scene(self) -> Scene:
        return self.setup.scene

    @property
    def grid(self):
        return self.setup.grid

    @property
    def density(self) -> torch.Tensor:
        """(C, nz, ny, nx) emission density of the target frame."""
        return self.setup.volume(self.x)

    def score(self, density: torch.Tensor | None = None) -> dict:
        """Held-out and training scores of ``density`` (default: this one) on the target frame,
        as :meth:`~flamerecon.fit.reconstruct.Reconstruction.score` gives them."""
        density = self.density if density is None else density
        metrics, _ = score(self.scene, density, self.grid, self.setup.train, self.setup.holdout,
                           self.setup.step, self.options.silhouette.as_dict())
        metrics["warnings"] = result_warnings(self.scene, density, metrics, self.setup.train + self.setup.holdout,
                                              *penalty_of(self.options.solver.as_dict(), self.record.get("l1", 0.0)),
                                              train=self.setup.train, step=self.setup.step,
                                              bbox=(self.grid.bbox_min, self.grid.bbox_max))
        return metrics


def solve_window(frames: Sequence[MotionFrame], target: int, options: ReconstructionOptions,
                 motion: MotionOptions, displacements: dict[int, Displacement] | None = None
                 ) -> MotionReconstruction:
    """The shared-density solve of frame ``target`` over the frames within ``motion.window``
    of it (module doc); the displacements are estimated when not given."""
    started = time.perf_counter()
    half = int(motion.window) // 2
    keep = [s for s in range(len(frames)) if abs(s - target) <= half]
    sub = [frames[s] for s in keep]
    t = keep.index(target)
    if displacements is None:
        displacements = estimate_window(sub, t, motion)
    else:
        displacements = {keep.index(s): d for s, d in displacements.items() if s in keep}
    weights = window_weights([s - target for s in keep], motion.decay)
    A, b = window_problem(sub, t, displacements, weights)
    here = sub[t].setup
    if len(sub) == 1:  # no neighbour: the single-frame reconstruction
        return MotionReconstruction(here, sub[t].fit.result.x, list(sub), t, {}, options,
                                    {"window": 1, "frames": [here.scene.meta.get("frame")], "weights": weights,
                                     "l1": sub[t].fit.l1, "motion": {}})
    s = options.solver
    l1 = (float(s.l1) if s.l1 is not None else float(s.l1_rel or 0.0) * lambda_max(A, b))
    problem = Problem(A, b, l1, grid_shape=here.grid.shape, voxel_index=here.voxel_index)
    result = make_solver(s.name, **s.params).solve(problem, x0=sub[t].fit.result.x.clone())
    x, debiased = debias(options.debias, A, b, result.x)
    record = {"window": int(motion.window), "frames": [f.setup.scene.meta.get("frame") for f in sub],
              "weights": weights, "l1": l1, "iterations": result.iterations, "converged": result.converged,
              "motion": {str(sub[k].setup.scene.meta.get("frame", k)): d.record() for k, d in displacements.items()},
              "debias": debiased, "seconds": time.perf_counter() - started}
    return MotionReconstruction(here, x, list(sub), t, {keep[k]: d for k, d in displacements.items()},
                                options, record)


def reconstruct_motion(scenes: Sequence[Scene], options: ReconstructionOptions | None = None,
                       motion: MotionOptions | None = None, target: int | None = None,
                       device: torch.device | str | None = None) -> MotionReconstruction:
    """Reconstruct frame ``scenes[target]`` (default: the middle one) of consecutive frames
    ``scenes`` with the frames within ``motion.window`` of it warped onto it (module doc).
    Each frame is first reconstructed on its own; ``motion.window=1`` returns the target's
    single-frame reconstruction. Sets torch's seed and thread count as the options say."""
    check_frame_inputs("reconstruct_motion", scenes, options, device, "consecutive frames in order")
    instance("reconstruct_motion.motion", motion, MotionOptions, null=True)
    options = (options or ReconstructionOptions()).check()
    motion = motion or MotionOptions()
    target = len(scenes) // 2 if target is None else target
    if not isinstance(target, int) or not 0 <= target < len(scenes):
        raise wrong_value("reconstruct_motion.target", target, f"an index of scenes in [0, {len(scenes) - 1}]")
    if options.solver.name not in MOTION_SOLVERS:
        raise ConfigError(f"solver.name: motion compensation solves with solver=tv or fista "
                          f"(got '{options.solver.name}')")
    if options.photometry.fit_gain or options.select.auto or list(options.grid.levels or []) or options.init:
        raise ConfigError("motion: photometry.fit_gain, select.auto, grid.levels and init are not supported "
                          "with motion compensation; leave them off")
    torch.manual_seed(int(options.seed))
    set_threads(options.threads)
    device = resolve_device(options.device if device is None else str(device))
    half = int(motion.window) // 2
    chosen = list(range(max(0, target - half), min(len(scenes), target + half + 1)))
    frames = prepare_window([scenes[s] for s in chosen], options, device)
    return solve_window(frames, chosen.index(target), options, motion)
