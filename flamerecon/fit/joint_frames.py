"""Several frames of a capture reconstructed jointly, time as a prior (the solve itself:
:mod:`flamerecon.solvers.temporal`).

Each frame is prepared as a single frame would be (its own camera refinement, silhouettes,
hull, operator and weights ``solver.l1_rel`` / ``solver.tv`` relative to its own
max(A^T P)), then all are solved together with the temporal weights of
:class:`JointFramesOptions`, relative like the solver's: w2 = ``l2`` * mean_t ||A_t||^2
(squared coupling against the data's curvature), w1 = ``tv`` * mean_t max(A_t^T P_t) (L1
coupling on the scale of l1). Every frame is then debiased as ``options.debias`` says.

    import flamerecon as fr
    scenes = [fr.load_scene({"name": "synthetic", "frame": t}) for t in range(3)]
    rec = fr.reconstruct_frames(scenes, fr.ReconstructionOptions(solver=...), fr.JointFramesOptions(l2=0.01))
    rec.frames[1].density                              # (C, nz, ny, nx) of the middle frame
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from itertools import pairwise

import numpy as np
import torch

from flamerecon.arguments import fields, instance
from flamerecon.device import resolve_device, set_threads
from flamerecon.errors import ConfigError
from flamerecon.fit.build import Setup, build, check_frame_inputs, make_problem, scene_grid
from flamerecon.fit.checks import check_before_work
from flamerecon.fit.debias import debias
from flamerecon.fit.option_rules import check_section
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import SolveHook, calibrated_scene
from flamerecon.scenes import Scene
from flamerecon.solvers import lambda_max
from flamerecon.solvers.base import power_norm_sq
from flamerecon.solvers.temporal import (
    FrameProblem,
    JointOptions,
    JointResult,
    estimate_shift,
    solve_joint,
)

JOINT_SOLVERS = ("tv", "fista")  # the per-frame objectives the joint solve extends


@dataclass(frozen=True)
class JointFramesOptions:
    """The ``temporal:`` node: relative weights ``l2`` (squared coupling) and ``tv`` (L1
    coupling) of neighbouring frames (module doc), the stopping ``tol`` on the iterate's
    relative change, and ``motion``: ``none`` couples voxel v of frame t with voxel v of t+1,
    ``shift`` with v + s, s the whole-cell shift (within ``max_shift`` cells) that best carries
    the uncoupled solve's frame t onto t+1."""

    l2: float = 0.01
    tv: float = 0.0
    tol: float = 1.0e-5
    motion: str = "none"
    max_shift: int = 3

    def __post_init__(self) -> None:
        check_section("temporal", self)


def check_joint(options: ReconstructionOptions) -> None:
    """Refuse what the joint solve does not do (each is one line naming the field)."""
    if options.solver.name not in JOINT_SOLVERS:
        raise ConfigError(f"solver.name: scene.frames solves frames jointly with solver=tv or fista "
                          f"(got '{options.solver.name}'); use one of them, or one run per scene.frame")
    if list(options.grid.levels or []):
        raise ConfigError("grid.levels: not supported with scene.frames; leave grid.levels=[]")
    if options.init:
        raise ConfigError("init: not supported with scene.frames; drop init=")
    if options.photometry.fit_gain:
        raise ConfigError("photometry.fit_gain: not supported with scene.frames; set it false")
    if options.select.auto:
        raise ConfigError("select.auto: not supported with scene.frames (one set of weights for all "
                          "frames); set select.auto=false, or choose weights on a single frame")


@dataclass
class PreparedFrames:
    """Every frame built as a single frame would be (one entry each)."""

    setups: list[Setup]
    problems: list[FrameProblem]
    l1s: list[float]
    norms_sq: list[float]  # ||A_t||^2 by power iteration
    calibrations: list[dict | None]  # each frame's calibration.refine record (None when off)


def prepare_frames(scenes: Sequence[Scene], options: ReconstructionOptions, device: torch.device) -> PreparedFrames:
    """Camera refinement, silhouettes, hull, operator and absolute weights of each frame (all
    on one grid box)."""
    setups, frames, l1s, calibrations = [], [], [], []
    for scene in scenes:
        scene, calibration = calibrated_scene(scene, options, device)
        calibrations.append(calibration)
        setup = build(scene, options, device)
        if setups and (setup.grid.resolution != setups[0].grid.resolution
                       or setup.grid.bbox_min != setups[0].grid.bbox_min
                       or setup.grid.bbox_max != setups[0].grid.bbox_max):
            raise ConfigError(f"scene.frames: frame {scene.meta.get('frame', len(setups))} has another grid "
                              "box than the first frame; set grid.bbox to one box for all frames")
        _, _, l1 = make_problem(options.solver, setup)
        mu = float(options.solver.params.get("tv", 0.0) or 0.0) * lambda_max(setup.operator, setup.pixels) \
            if options.solver.name == "tv" else 0.0
        frames.append(FrameProblem(setup.operator, setup.pixels, l1, mu, setup.grid.shape, setup.voxel_index))
        setups.append(setup)
        l1s.append(l1)
    norms_sq = [power_norm_sq(f.A, int(f.voxel_index.numel()), device, f.b.dtype) for f in frames]
    return PreparedFrames(setups, frames, l1s, norms_sq, calibrations)


def joint_solve_options(options: ReconstructionOptions, joint: JointFramesOptions,
                        prepared: PreparedFrames) -> JointOptions:
    """Absolute temporal weights (module doc) and the solver's iteration budget."""
    scale = float(np.mean([lambda_max(f.A, f.b) for f in prepared.problems]))
    s = options.solver.params
    step = s.get("dual_step")
    return JointOptions(
        l2=joint.l2 * float(np.mean(prepared.norms_sq)), tv=joint.tv * scale,
        max_iters=int(s.get("max_iters", 300)), tol=float(joint.tol), check_every=int(s.get("check_every", 10)),
        dual_step=float(step) if step is not None else max(0.1, (float(s.get("tv", 0.0)) / 1e-3) ** 0.5),
        max_seconds=s.get("max_seconds"),
    )


def solve_frames(prepared: PreparedFrames, opts: JointOptions, motion: str = "none", max_shift: int = 3,
                 callback: Callable | None = None) -> tuple[JointResult, list[tuple[int, int, int]] | None]:
    """The joint solve; with ``motion="shift"`` first the uncoupled solve, then one whole-cell
    shift per neighbouring pair estimated from its densities
    (:func:`~flamerecon.solvers.temporal.estimate_shift`), then the coupled solve along those
    shifts from the uncoupled solution. Returns the result (seconds: both solves) and the
    shifts (None without motion)."""
    if motion == "none":
        return solve_joint(prepared.problems, opts, norms_sq=prepared.norms_sq, callback=callback), None
    if motion != "shift":
        raise ConfigError(f"temporal.motion: unknown '{motion}'; use none or shift")
    free = solve_joint(prepared.problems, replace(opts, l2=0.0, tv=0.0), norms_sq=prepared.norms_sq)
    volumes = [s.volume(x).mean(0) for s, x in zip(prepared.setups, free.xs)]
    shifts = [estimate_shift(a, b, max_shift) for a, b in pairwise(volumes)]
    result = solve_joint(prepared.problems, opts, x0=free.xs, norms_sq=prepared.norms_sq,
                         callback=callback, shifts=shifts)
    result.seconds += free.seconds
    return result, shifts


@dataclass
class JointFrame:
    """One frame of a joint reconstruction: its (calibrated) scene's ``setup``, the debiased
    hull values ``x`` (M, C), its absolute ``l1`` and the debias and calibration records."""

    setup: Setup
    x: torch.Tensor
    l1: float
    debias: dict | None
    calibration: dict | None

    @property
    def scene(self) -> Scene:
        return self.setup.scene

    @property
    def density(self) -> torch.Tensor:
        """(C, nz, ny, nx) emission density on ``setup.grid``."""
        return self.setup.volume(self.x)


@dataclass
class JointReconstruction:
    """What :func:`reconstruct_frames` returns: the frames in order, the joint solve's result
    and its record (frames, absolute and relative weights, motion shifts)."""

    frames: list[JointFrame]
    result: JointResult
    record: dict

    def __post_init__(self) -> None:
        fields(self)


def reconstruct_frames(scenes: Sequence[Scene], options: ReconstructionOptions | None = None,
                       joint: JointFramesOptions | None = None, hook: SolveHook | None = None,
                       device: torch.device | str | None = None) -> JointReconstruction:
    """Reconstruct consecutive frames ``scenes`` (the same capture, in order) jointly: each
    prepared as :func:`~flamerecon.fit.reconstruct.reconstruct` would, solved together with the
    temporal coupling of ``joint`` through ``hook.joint`` (default: solve only), each frame then
    debiased. Sets torch's seed and thread count as the options say."""
    check_frame_inputs("reconstruct_frames", scenes, options, device, "the frames in order")
    instance("reconstruct_frames.joint", joint, JointFramesOptions, null=True)
    instance("reconstruct_frames.hook", hook, SolveHook, null=True)
    options = (options or ReconstructionOptions()).check()
    joint = joint or JointFramesOptions()
    hook = hook or SolveHook()
    check_joint(options)
    torch.manual_seed(int(options.seed))
    set_threads(options.threads)
    device = resolve_device(options.device if device is None else str(device))
    for scene in scenes:
        check_before_work(scene, options, scene_grid(options.grid, scene))
    hook.begin()
    prepared = prepare_frames(scenes, options, device)
    opts = joint_solve_options(options, joint, prepared)
    shifts: list = []

    def run(callback: Callable | None) -> JointResult:
        result, found = solve_frames(prepared, opts, joint.motion, joint.max_shift, callback)
        shifts.append(found)
        return result

    result = hook.joint(prepared.setups, run)
    frame_numbers = [s.scene.meta.get("frame") for s in prepared.setups]
    record = {"frames": [frame_numbers[0], frame_numbers[-1]], "l2": opts.l2, "tv": opts.tv,
              "l2_rel": float(joint.l2), "tv_rel": float(joint.tv),
              "coupled_on": "pairwise intersection of neighbouring frames' hulls", "shifts": shifts[0]}
    frames = []
    for setup, x, l1, calibration in zip(prepared.setups, result.xs, prepared.l1s, prepared.calibrations):
        x, debiased = debias(options.debias, setup.operator, setup.pixels, x)
        frames.append(JointFrame(setup, x, l1, debiased, calibration))
    return JointReconstruction(frames, result, record)
