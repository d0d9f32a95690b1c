"""reconstruct(scene, options): the one orchestration path of a reconstruction — camera
refinement, warm start, coarse grid levels, weight selection, the solve, photometry refits and
debiasing. Every solve of it (coarse levels, the final grid, each refit) goes through a
:class:`SolveHook`; the run layer's hook adds the run folder, TensorBoard, checkpoints, resume
and the divergence guard (:mod:`flamerecon.run.hook`), the default one just solves."""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from flamerecon.arguments import describe, fields, instance, tensor, value, wrong_value
from flamerecon.device import resolve_device, set_threads
from flamerecon.errors import ArgumentError, ConfigError, FlameReconError
from flamerecon.evaluate.result_warnings import penalty_of, result_warnings
from flamerecon.evaluate.scores import score
from flamerecon.fit.build import (
    BUILD_OPTIONS,
    Setup,
    build,
    check_inputs,
    check_solver_name,
    hull_values,
    init_volume,
    make_problem,
    scene_grid,
    scene_masks,
    split_views,
)
from flamerecon.fit.capture_calibration import (
    CaptureCalibration,
    capture_refinement,
    file_cameras,
    file_offsets,
)
from flamerecon.fit.checks import check_before_work, check_grid_memory, density_fault, memory_budget
from flamerecon.fit.debias import DebiasOptions, debias
from flamerecon.fit.levels import LadderOptions, Level, ladder_rungs, plan_levels
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.refine_cameras import CalibrationFrame, correction_report, refine, with_cameras
from flamerecon.fit.weight_selection import select_weights
from flamerecon.fit.workload import check_workload
from flamerecon.geometry.cameras import camera_subset, cameras_to, resized_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.photometry import fit_gain_offset_rows, normalize_gains
from flamerecon.progress import Progress
from flamerecon.rules import integer, number
from flamerecon.scenes import Scene, capture_frames, load_downscaled
from flamerecon.solvers import Problem, Solver, SolveResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stage:
    """Which solve of a reconstruction: grid ``level`` (0 = coarsest; ``levels`` = the final
    grid) and ``round`` (0: the solve, r >= 1: photometry refit r on the final grid)."""

    level: int
    levels: int
    round: int = 0

    def __post_init__(self) -> None:
        for name in ("levels", "level", "round"):
            value(f"Stage.{name}", getattr(self, name), integer(0))
        if self.level > self.levels:
            raise wrong_value("Stage.level", self.level, f"<= levels ({self.levels}): the final grid is level {self.levels}")

    @property
    def final(self) -> bool:
        return self.level == self.levels

    @property
    def tag_root(self) -> str:
        """TensorBoard tag prefix: ``""`` for the final grid's solve, ``refit<r>/`` for its
        photometry refit r, ``level<i>/`` for coarse level i."""
        if not self.final:
            return f"level{self.level}/"
        return f"refit{self.round}/" if self.round else ""

    def __str__(self) -> str:
        where = "the final grid" if self.final else f"coarse level grid.levels[{self.level}]"
        return where + (f", photometry refit {self.round}" if self.round else "")


@dataclass
class ResumePoint:
    """Where an interrupted reconstruction continues: the stage its checkpoint was written in
    and the ``carry`` the core handed to that stage's solve."""

    level: int
    round: int = 0
    carry: dict = field(default_factory=dict)


class SolveHook:
    """What every solve of :func:`reconstruct` goes through. This one solves and nothing
    else; the run layer's (:class:`flamerecon.run.hook.RunHook`) monitors, checkpoints,
    guards and resumes.

    :meth:`solve` gets the stage, its problem and solver, the warm start ``x0`` (M, C) or None,
    and ``carry``: what the core needs to continue after this stage if it is resumed (a hook
    that checkpoints stores it). A hook may stop a solve early: it then returns the last good
    iterate with ``SolveResult.stopped`` set, and the reconstruction ends after that stage.
    """

    def solve(self, stage: Stage, setup: Setup, problem: Problem, solver: Solver,
              x0: torch.Tensor | None, carry: dict) -> SolveResult:
        for name, given, kind in (("stage", stage, Stage), ("setup", setup, Setup), ("problem", problem, Problem),
                                  ("solver", solver, Solver), ("carry", carry, dict)):
            instance(f"SolveHook.solve.{name}", given, kind)
        x0 = tensor("SolveHook.solve.x0", x0, "(M, C) hull values", shape=tuple(problem.A.shape[1:]) + (
            problem.b.shape[1],), finite=True, null=True)
        return solver.solve(problem, x0=x0)

    def resume(self) -> ResumePoint | None:
        """The stage to continue from (None: start afresh)."""
        return None

    def begin(self) -> None:
        """Called once, when the inputs have passed every check made before any work (the run
        layer's hook prints the composed config here); this one does nothing."""

    def joint(self, setups: list[Setup], solve: Callable[[Callable | None], Any]) -> Any:
        """The joint solve of several frames (:func:`flamerecon.fit.joint_frames.reconstruct_frames`):
        ``solve(callback)`` runs it and returns its
        :class:`~flamerecon.solvers.temporal.JointResult`, calling ``callback(iteration, xs,
        info)`` at every check when one is given; this hook gives none."""
        return solve(None)


@dataclass
class Photometry:
    """Per training camera ``image = gain * integral + offset`` (``gain``, ``offset``: (T,))."""

    gain: torch.Tensor
    offset: torch.Tensor
    iterations: list[int]  # of each re-solve
    solve_iterations: int = 0  # of the solve before the first refit

    def per_view(self, setup: Setup) -> dict[str, tuple[float, float]]:
        """{view name: (gain, offset)} for every view; held-out views get (1, 0)."""
        out = {name: (1.0, 0.0) for name in setup.scene.views}
        for k, v in enumerate(setup.train):
            out[setup.scene.views[v]] = (float(self.gain[k]), float(self.offset[k]))
        return out


@dataclass
class Fit:
    """A density fitted on one :class:`~flamerecon.fit.build.Setup`."""

    result: SolveResult  # the last solve (x: the debiased density's hull values (M, C))
    l1: float  # absolute L1 weight
    options: ReconstructionOptions  # the options solved with (weights as selected)
    photometry: Photometry | None = None
    selection: dict | None = None  # the weight selection's record
    debias: dict | None = None  # the debiasing's record
    seconds: dict = field(default_factory=dict)  # wall time: selection, solve, photometry

    def __post_init__(self) -> None:
        fields(self)
        value("Fit.l1", self.l1, number(0))


@dataclass
class Reconstruction:
    """What :func:`reconstruct` returns: the density on ``setup`` and how it was found."""

    scene: Scene  # with the refined cameras when calibration refinement ran
    setup: Setup
    fit: Fit
    levels: list[dict] = field(default_factory=list)  # one record per grid (with grid.levels)
    calibration: dict | None = None  # the camera refinement's record
    timing: dict = field(default_factory=dict)  # wall seconds per step
    memory_bound: int | None = None  # bytes: the bound of the process's peak told before the work

    def __post_init__(self) -> None:
        fields(self)

    @property
    def options(self) -> ReconstructionOptions:
        return self.fit.options

    @property
    def grid(self) -> VoxelGrid:
        return self.setup.grid

    @functools.cached_property
    def density(self) -> torch.Tensor:
        """(C, nz, ny, nx) emission density on :attr:`grid`: one tensor, made on first use, so
        that an edit in place (a scale, a mask, a clamp) is what :meth:`score`, ``fr.score``,
        ``fr.export`` and ``fr.render`` of it see."""
        return self.setup.volume(self.fit.result.x)

    @property
    def stopped(self) -> str | None:
        """Why the last solve stopped early (the hook's guard), None when it finished."""
        return self.fit.result.stopped

    def score(self) -> dict:
        """Metrics of the density: held-out and training PSNR/SSIM (see
        :func:`flamerecon.evaluate.scores.score`), volume errors when the scene has a truth,
        ``warnings`` (:func:`~flamerecon.evaluate.result_warnings.result_warnings`)."""
        photometry = self.fit.photometry.per_view(self.setup) if self.fit.photometry else None
        metrics, _ = score(self.scene, self.density, self.grid, self.setup.train, self.setup.holdout,
                           self.setup.step, self.options.silhouette.as_dict(), photometry,
                           self.setup.training_pixels(self.density))
        metrics["warnings"] = result_warnings(
            self.scene, self.density, {**metrics, "calibration": self.calibration}, self.setup.train + self.setup.holdout,
            *penalty_of(self.options.solver.as_dict(), self.fit.l1), train=self.setup.train, step=self.setup.step,
            bbox=(self.grid.bbox_min, self.grid.bbox_max))
        return metrics


def choose_weights(options: ReconstructionOptions, setup: Setup) -> tuple[ReconstructionOptions, dict | None]:
    """With ``select.auto`` and candidates for the solver: the options with the solver weights
    that leave-one-view-out over the training views prefers
    (:func:`~flamerecon.fit.weight_selection.select_weights`), and the selection's record; else
    ``options`` unchanged and None."""
    solver = options.solver
    selection = options.select.for_solver(solver.name)
    if selection is None:
        return options, None
    check_solver_name(solver.name)
    if len(setup.train) < 2:
        raise ConfigError(f"select.auto: choosing weights needs at least two training views, "
                          f"got {len(setup.train)}; set select.auto=false")
    base = {k: v for k, v in solver.as_dict().items() if k != "name"}
    images = setup.scene.images[setup.train].to(setup.pixels)
    energy = (images.double() ** 2).sum((-2, -1))  # (T, C)
    H, W = setup.scene.image_size
    try:
        found = select_weights(solver.name, base, selection, options.debias, setup.operator,
                               setup.pixels, setup.row_view, energy, H * W,
                               [setup.scene.views[v] for v in setup.train],
                               {"grid_shape": setup.grid.shape, "voxel_index": setup.voxel_index})
    except (TypeError, ValueError) as err:  # a misspelt candidate key, as make_solver says it
        raise ConfigError(f"select.candidates.{solver.name}: {err}") from err
    log.info("weights chosen by leave-one-view-out over the training views: %s", found.chosen)
    return options.replace(solver=solver.with_values(**found.chosen)), found.record()


def fit(setup: Setup, options: ReconstructionOptions, x0: torch.Tensor | None = None,
        hook: SolveHook | None = None, stage: Stage | None = None, carry: dict | None = None) -> Fit:
    """Fit a density on ``setup``: weights chosen (``select``), the solve, photometry refits
    (``photometry.fit_gain``), ``debias``; each solve through ``hook`` at ``stage`` (default:
    the final grid without coarse levels), from ``x0`` (M, C) or 0. ``carry``: what a resumed
    run needs of the stages before (see :class:`SolveHook`). Sets torch's thread count as
    ``options.threads`` says."""
    x0 = check_fit(setup, options, x0, hook, stage, carry)
    set_threads(options.threads)
    hook = hook or SolveHook()
    stage = stage or Stage(0, 0)
    carry = dict(carry or {})
    resumed = hook.resume()
    refit_at = resumed.round if resumed is not None and resumed.level == stage.level else 0
    seconds: dict = {}
    clock = time.perf_counter()
    options, selection = choose_weights(options, setup)
    if selection is not None:
        seconds["selection"] = time.perf_counter() - clock
    problem, solver, l1 = make_problem(options.solver, setup)
    result = None
    if refit_at == 0:
        clock = time.perf_counter()
        result = hook.solve(stage, setup, problem, solver, x0, carry)
        seconds["solve"] = time.perf_counter() - clock
        if result.stopped is not None:
            return Fit(result, l1, options, None, selection, None, seconds)
    clock = time.perf_counter()
    restored = resumed.carry["photometry"] if refit_at else None
    result, photometry = fit_photometry(options, setup, problem, solver, result, hook, stage, carry,
                                        restored, refit_at)
    if photometry is not None:
        seconds["photometry"] = time.perf_counter() - clock
    debiased = None
    if result.stopped is None:
        result.x, debiased = debias(options.debias, setup.operator, setup.pixels, result.x)
    return Fit(result, l1, options, photometry, selection, debiased, seconds)


def check_fit(setup: Setup, options: ReconstructionOptions, x0, hook, stage, carry) -> torch.Tensor | None:
    """Refuse arguments :func:`fit` cannot take, and options that disagree with those
    ``setup`` was built with in what :func:`~flamerecon.fit.build.build` reads
    (:data:`~flamerecon.fit.build.BUILD_OPTIONS`); returns ``x0`` on the setup's device and
    dtype."""
    instance("fit.setup", setup, Setup)
    instance("fit.options", options, ReconstructionOptions,
             "a ReconstructionOptions (a dict of options goes through ReconstructionOptions.from_dict)")
    instance("fit.hook", hook, SolveHook, null=True)
    instance("fit.stage", stage, Stage, null=True)
    instance("fit.carry", carry, dict, null=True)
    built = setup.options
    for name in BUILD_OPTIONS if built is not None else ():
        if getattr(options, name) != getattr(built, name):
            raise ArgumentError(
                f"fit.options: its {name} is {describe(getattr(options, name))} but the setup was built with "
                f"{describe(getattr(built, name))}; fit with the options given to build, or build again")
    shape = (int(setup.voxel_index.numel()), int(setup.pixels.shape[1]))
    x0 = tensor("fit.x0", x0, "(M, C) hull values of the setup", shape=shape, finite=True, null=True)
    return None if x0 is None else x0.to(setup.pixels)


def fit_photometry(options: ReconstructionOptions, setup: Setup, problem: Problem, solver: Solver,
                   result: SolveResult | None, hook: SolveHook, stage: Stage, carry: dict,
                   resumed: dict | None = None, resumed_round: int = 0
                   ) -> tuple[SolveResult, Photometry | None]:
    """With ``photometry.fit_gain``: ``photometry.rounds`` times, fit each training camera's
    gain and offset to the current density's line integrals on its rows (gains normalized to
    geometric mean 1, so held-out cameras keep gain 1 and offset 0), then solve again, through
    ``hook``, from the current density on ``(pixels - offset) / gain``. Returns the last solve
    and the fitted photometry (None when off). ``resumed``: the ``carry["photometry"]`` of the
    checkpoint written in refit ``resumed_round`` (gain, offset, iterations and seconds
    before it), whose solve the hook continues (``result``: None)."""
    opts = options.photometry
    if not opts.fit_gain:
        return result, None
    rounds = int(opts.rounds)
    if rounds < 1:
        raise ConfigError(f"photometry.rounds: must be at least 1 when photometry.fit_gain is on, got {rounds}")
    T = len(setup.train)
    first = 1 if resumed is None else resumed_round
    iterations = [] if resumed is None else list(resumed["iterations"])
    solved = result.iterations if resumed is None else int(resumed["solve_iterations"])
    seconds = result.seconds if resumed is None else float(resumed["seconds"])
    gain = offset = None
    if resumed is not None:
        gain, offset = (torch.as_tensor(resumed[k]).to(setup.pixels) for k in ("gain", "offset"))
    for r in range(first, rounds + 1):
        if not (resumed is not None and r == first):
            with torch.no_grad():
                predicted = setup.operator.forward(result.x)
            gain, offset = fit_gain_offset_rows(predicted, setup.pixels, setup.row_view, T, bool(opts.fit_offset))
            if not bool((gain > 0).all()):
                bad = [setup.scene.views[setup.train[k]] for k in (gain <= 0).nonzero().flatten().tolist()]
                raise ConfigError(f"photometry.fit_gain: cameras {bad} got a gain <= 0 (their images do not "
                                  "follow the density's line integrals); run with photometry.fit_gain=false")
            gain = normalize_gains(gain)
        b = (setup.pixels - offset[setup.row_view, None]) / gain[setup.row_view, None]
        again = Problem(setup.operator, b, problem.l1, grid_shape=problem.grid_shape,
                        voxel_index=problem.voxel_index)
        state = {"gain": gain.cpu(), "offset": offset.cpu(), "iterations": list(iterations), "seconds": seconds,
                 "solve_iterations": solved}
        x0 = None if result is None else result.x
        result = hook.solve(replace(stage, round=r), setup, again, solver, x0, {**carry, "photometry": state})
        iterations.append(result.iterations)
        seconds += result.seconds
        if result.stopped is not None:
            break
    result.seconds = seconds
    return result, Photometry(gain.cpu(), offset.cpu(), iterations, solved)


def level_options(options: ReconstructionOptions, max_iters: int | None, weight_ratio: float) -> ReconstructionOptions:
    """``options`` for a coarse level: ``max_iters`` set to its budget (unchanged for None); an
    absolute ``solver.l1`` (the final level's) times ``weight_ratio``: the level's cell volume
    over the final grid's, times its pixels over the final images' for a rung of the ladder,
    the weight under which the coarse problem is the final one restricted to densities constant
    on the coarse cells (``l1_rel`` needs nothing: max(A^T P) of each level scales the same way)."""
    change: dict = {}
    if max_iters is not None:
        change["max_iters"] = max_iters
    if options.solver.l1:
        change["l1"] = float(options.solver.l1) * weight_ratio
    return options.replace(solver=options.solver.with_values(**change)) if change else options


def levels_of(scene: Scene, options: ReconstructionOptions) -> list[Level]:
    """The solves before the run's own (:func:`~flamerecon.fit.levels.plan_levels`): the
    ladder's rungs that run for ``scene``, then ``grid.levels``."""
    return plan_levels(scene, options.ladder, list(options.grid.levels) or None, options.grid.level_iters,
                       scene_grid(options.grid, scene))


def level_scene(scene: Scene, level: Level) -> Scene:
    """The scene a level solves: ``scene`` itself, or for a rung its frame loaded at the rung's
    downscale with ``scene``'s cameras (refined ones too) resized to those images."""
    if level.downscale is None:
        return scene
    coarse = load_downscaled(scene, level.downscale)
    return replace(coarse, cameras=resized_cameras(scene.cameras, *coarse.image_size))


def coarse_levels(scene: Scene, options: ReconstructionOptions, device: torch.device,
                  volume: torch.Tensor | None = None, first: int = 0, hook: SolveHook | None = None,
                  records: list[dict] | None = None) -> torch.Tensor | None:
    """Solve the levels before the run's own (:func:`levels_of`: the ladder's rungs, then
    ``grid.levels``) from ``first`` on, coarsest first, each on its own scene
    (:func:`level_scene`), visual hull and operator (same box, silhouettes and solver, see
    :func:`level_options` for its L1 weight and iteration budget), each through ``hook``, each
    starting from the previous density resampled onto it (the first from ``volume``, or 0);
    each level's record is appended to ``records``. Returns the last level's density (C, nz,
    ny, nx), or ``volume`` when there are no levels."""
    hook = hook or SolveHook()
    records = [] if records is None else records
    fine = scene_grid(options.grid, scene)
    levels = levels_of(scene, options)
    H, W = scene.image_size
    for k in range(first, len(levels)):
        where = level_scene(scene, levels[k])
        h, w = where.image_size
        here = level_options(options, levels[k].iters, fine.num_voxels / levels[k].grid.num_voxels * h * w / (H * W))
        setup = build(where, here, device, levels[k].grid)
        x0 = None if volume is None else hull_values(volume, setup.grid, setup.voxel_index)
        problem, solver, l1 = make_problem(here.solver, setup)
        result = hook.solve(Stage(k, len(levels)), setup, problem, solver, x0, {"level_records": list(records)})
        records.append(level_record(setup, l1, result))
        volume = setup.volume(result.x)
        del setup, result, problem, where  # free this level's operator and images before the next
    return volume


def level_record(setup: Setup, l1: float, result: SolveResult) -> dict:
    """One level's entry in metrics.json's ``solver.levels``."""
    H, W = setup.scene.image_size
    return {"resolution": list(setup.grid.resolution), "image": [W, H], "voxels": int(setup.voxel_index.numel()),
            "l1": l1, "iterations": result.iterations, "seconds": result.seconds,
            "setup_seconds": setup.seconds, "objective": result.objective,
            "converged": result.converged}


def warm_start(scene: Scene, options: ReconstructionOptions, device: torch.device, setup: Setup) -> torch.Tensor | None:
    """x0 (M, C) for the final ``setup`` without a hook: the ``init`` run's density and/or the
    solutions of the levels before it (see :func:`coarse_levels`); None for a cold start."""
    levels = levels_of(scene, options)
    volume = (init_volume(options.init, levels[0].grid if levels else setup.grid, setup.pixels.shape[1])
              if options.init else None)
    volume = coarse_levels(scene, options, device, volume)
    return None if volume is None else hull_values(volume, setup.grid, setup.voxel_index)


def calibrated_scene(scene: Scene, options: ReconstructionOptions, device: torch.device
                     ) -> tuple[Scene, dict | None]:
    """With ``calibration.refine`` other than ``none``: ``scene`` with its training cameras
    refined through the renderer (:func:`~flamerecon.fit.refine_cameras.refine`, each density
    solve as :func:`build` and :func:`fit` do it, on the grid of ``calibration.resolution``
    (default: the final grid's), a ``refit`` debias done by the gain) to this frame, or with
    ``calibration.frames`` to those frames of the capture (once per capture, kept in a file:
    :func:`~flamerecon.fit.capture_calibration.capture_refinement`); with ``calibration.file``
    read from that cameras.json instead. Refinement starts from the capture's own cameras, also
    for a scene that carries refined ones (a loaded run's: ``meta["calibrated_cameras"]``);
    held-out cameras keep their own. Returns the scene and the record for metrics.json's
    ``calibration`` (where the cameras came from, corrections per camera, the scores of this
    frame's density solved with the capture's own cameras, with cameras from a file only for
    ``calibration.score_before``); ``(scene, None)`` when off."""
    refining = options.calibration
    if refining.refine == "none" and not refining.file:
        return scene, None
    rungs = ladder_rungs(scene, options.ladder, scene_grid(options.grid, scene))
    if rungs:  # fitted on the coarsest rung's images, as a run at that downscale fits them
        coarse = options.replace(ladder=LadderOptions(), grid=replace(options.grid, resolution=rungs[0].grid.resolution))
        fitted, record = calibrated_scene(load_downscaled(scene, rungs[0].downscale), coarse, device)
        own = scene.meta.get("calibrated_cameras", scene.cameras)
        return (replace(scene, cameras=resized_cameras(fitted.cameras, *scene.image_size),
                        meta={**scene.meta, "calibrated_cameras": own}),
                {**record, "downscale": rungs[0].downscale})
    started = time.perf_counter()
    if refining.frames == "auto":
        refining = refining.for_capture(capture_frames(scene))
        options = options.replace(calibration=refining)
    if "calibrated_cameras" in scene.meta:
        scene = replace(scene, cameras=scene.meta["calibrated_cameras"],
                        meta={k: v for k, v in scene.meta.items() if k != "calibrated_cameras"})
    train, holdout = split_views(scene, options)
    grid = scene_grid(replace(options.grid, resolution=refining.resolution or options.grid.resolution), scene)
    if refining.resolution:  # its own grid: refused naming its own option
        check_grid_memory(grid, len(scene.views), device, memory_budget(device, options.projector.max_memory_gb),
                          "calibration.resolution")
    step = float(options.projector.step)
    # the densities the cameras are fitted to: an unpenalised refit would fit part of the
    # cameras' errors into them (held-out train02, ScalarFlow frame 35: 31.84 dB against 33.23
    # with the gain), so they keep the penalised structure, only its level debiased
    fitting = options.replace(debias=DebiasOptions("gain")) if options.debias.method == "refit" else options
    # the cameras change at every round of the fit: their operators are not kept (projector.reuse)
    fitting = fitting.replace(projector=replace(fitting.projector, reuse=False))

    def capture_choice(cameras, sources: list[Scene], which: str) -> dict | None:
        """With select.auto: the selection record of the weights whose leave-one-view-out
        PSNR, averaged over the calibration frames ``sources`` solved with ``cameras`` (``which``:
        the capture's own, for the fit's densities, then the fitted ones: chosen with the
        capture's own cameras the weights run stronger, as the cameras' errors look like noise),
        is best; None when off."""
        if options.select.for_solver(options.solver.name) is None:
            return None
        tables = []
        progress = Progress(f"the capture's weights on its calibration frames, with {which} cameras", len(sources),
                            "frame")
        for source in sources:
            fitted = replace(source, cameras=cameras_to(cameras, "cpu"))
            tables.append(choose_weights(options, build(fitted, options, device, grid))[1]["candidates"])
            progress.step(f"frame {source.meta.get('frame')}")
        frames = [str(source.meta.get("frame")) for source in sources]
        table = [{"overrides": rows[0]["overrides"], "psnr": sum(r["psnr"] for r in rows) / len(rows),
                  "folds": {view: sum(r["folds"][view] for r in rows) / len(rows) for view in rows[0]["folds"]}}
                 for rows in zip(*tables)]  # each averaged over the frames
        best = max(range(len(table)), key=lambda k: table[k]["psnr"])
        return {"chosen": dict(table[best]["overrides"]), "candidates": table, "frames": [int(f) for f in frames]}

    def frame_of(source: Scene, weights: dict | None = None) -> CalibrationFrame:
        """The camera fit's view of frame ``source``: its densities solved with ``weights`` (the
        capture's, chosen on every calibration frame), else with the weights select.auto
        chooses in the frame's first solve."""
        images = source.images.to(device)
        chosen: list[dict] = [] if weights is None else [weights]  # the weights select.auto chose, or given

        def solve_density(views: list[int], cameras, start: torch.Tensor | None) -> torch.Tensor:
            fold = fitting.replace(holdout=tuple(name for i, name in enumerate(scene.views) if i not in views))
            if chosen:  # weights are chosen once per frame (or given), not at every solve
                fold = fold.replace(solver=fold.solver.with_values(**chosen[0]), select=replace(fold.select, auto=False))
            budget = refining.first_iterations if start is None else refining.solve_iterations
            if budget is not None and "max_iters" in fold.solver.params:
                fold = fold.replace(solver=fold.solver.with_values(max_iters=budget))
            setup = build(replace(source, cameras=with_cameras(scene.cameras, views, cameras)), fold, device, grid)
            x0 = None if start is None else hull_values(start, grid, setup.voxel_index)
            fitted = fit(setup, fold, x0)
            if start is None and not chosen and fitted.selection is not None:
                chosen.append(dict(fitted.selection["chosen"]))
            return setup.volume(fitted.result.x)

        return CalibrationFrame(images, scene_masks(source, images, options), solve_density)

    this = frame_of(scene)
    refined_views = list(train)  # the cameras the fit corrects: the training ones, every one for a rig
    if refining.rig:
        frame = scene.meta.get("config", {}).get("frame", scene.meta.get("frame"))
        if not refining.file and frame in refining.frames:
            raise ConfigError(f"calibration.rig: frame {frame} is reconstructed and one of calibration.frames "
                              f"{list(refining.frames)}, so its held-out views would enter the camera fit; "
                              "fit the rig to other frames")
        refined_views = list(range(len(scene.views)))
    if refining.file:  # a rig's file gives every camera, the held-out ones too
        found = CaptureCalibration(file_cameras(refining.file, scene, refined_views), [], "read",
                                   Path(refining.file), offsets=file_offsets(refining.file, scene.views))
    elif refining.frames:
        found = capture_refinement(scene, refined_views, grid, options, device, frame_of, capture_choice)
    else:
        fitted = refine(cameras_to(scene.cameras, device), train, [this], grid, refining, step)
        found = CaptureCalibration(fitted.cameras, fitted.history, "fitted", None)
        initial = fitted.initial_volume
    if found.file is not None:
        initial = (this.solve(list(train), cameras_to(camera_subset(scene.cameras, train), device), None)
                   if refining.score_before else None)
    refined = replace(scene, cameras=cameras_to(found.cameras, "cpu"),
                      meta={**scene.meta, "calibrated_cameras": scene.cameras})
    report = correction_report(camera_subset(scene.cameras, refined_views),
                               camera_subset(refined.cameras, refined_views), grid)
    record = {
        "refine": refining.refine, "frames": list(refining.frames), "rig": bool(refining.rig), "source": found.source,
        "file": None if found.file is None else str(found.file), "rounds": found.history,
        "cameras": {scene.views[v]: r for v, r in zip(refined_views, report)},
    }
    if found.selection:
        record["selection"] = found.selection
    if found.offsets:  # each camera's pose offset, measured with the fit (fit/pose_uncertainty.py)
        record["poses"] = {name: offset.record() for name, offset in found.offsets.items()}
    if initial is not None:
        before, _ = score(scene, initial, grid, train, holdout, step, options.silhouette.as_dict())
        record.update(train_psnr_before=mean_of(before["train"], "psnr"),
                      heldout_psnr_before=mean_of(before["heldout"], "psnr"))
    record["seconds"] = time.perf_counter() - started
    return refined, record


def with_capture_weights(options: ReconstructionOptions, calibration: dict | None) -> ReconstructionOptions:
    """With ``select.auto`` for the run's solver and a capture calibration that holds the weights
    it chose on the calibration frames (``calibration["selection"]``): ``options`` with those
    weights and ``select.auto`` off: weights are chosen once per capture, not at every frame."""
    selection = (calibration or {}).get("selection")
    if not selection or options.select.for_solver(options.solver.name) is None:
        return options
    weights = selection.get("chosen") if isinstance(selection, dict) else None
    try:
        solver = options.solver.with_values(**weights)
    except (FlameReconError, TypeError) as err:
        raise ConfigError(f"{calibration.get('file')}: its chosen weights {weights} do not fit solver "
                          f"{options.solver.name} ({err}); delete the file to fit the capture again") from None
    log.info("weights chosen once for the capture on calibration.frames %s: %s", calibration.get("frames"), weights)
    return options.replace(solver=solver, select=replace(options.select, auto=False))


def mean_of(per_view: dict[str, dict[str, float]], key: str) -> float:
    """The mean of ``key`` over the views of a metrics table (NaN for none)."""
    vals = [v[key] for v in per_view.values()]
    return sum(vals) / len(vals) if vals else math.nan


def reconstruct(scene: Scene, options: ReconstructionOptions | None = None, hook: SolveHook | None = None,
                device: torch.device | str | None = None, init: torch.Tensor | None = None) -> Reconstruction:
    """Reconstruct ``scene``: camera refinement (``calibration``), the warm start (``init``, a
    density (C, nz', ny', nx') on the grid's box such as the previous frame's, else
    ``options.init``'s run), the coarse levels (``grid.levels``), then :func:`fit` on the
    final grid; every solve through ``hook`` (default: solve only). Sets torch's seed and
    thread count as the options say. Returns the :class:`Reconstruction` (with ``stopped``
    set when the hook stopped a solve early: the later steps are then skipped)."""
    check_inputs("reconstruct", scene, options, device)
    instance("reconstruct.hook", hook, SolveHook, null=True)
    init = tensor("reconstruct.init", init, "(C, nz, ny, nx) density on the grid's box", ndim=4, finite=True,
                  null=True)
    if init is not None and init.shape[0] != scene.images.shape[1]:
        raise wrong_value("reconstruct.init", init, f"(C, nz, ny, nx) with C = {scene.images.shape[1]}, the "
                          "scene's channels")
    fault = None if init is None else density_fault(init, math.dist(scene.bbox_min, scene.bbox_max))
    if fault is not None:
        raise ArgumentError(f"reconstruct.init: {describe(init)} {fault}")
    options = (options or ReconstructionOptions()).check()
    hook = hook or SolveHook()
    check_solver_name(options.solver.name)
    torch.manual_seed(int(options.seed))
    set_threads(options.threads)
    device = resolve_device(options.device if device is None else str(device))
    fine = scene_grid(options.grid, scene)  # camera refinement keeps the box
    levels = levels_of(scene, options)  # refuses bad levels and budgets before any work
    resumed = hook.resume()
    first = 0 if resumed is None else min(resumed.level, len(levels))
    records: list[dict] = [] if resumed is None else list(resumed.carry.get("level_records", []))
    volume = None if resumed is not None else init
    if volume is None and resumed is None and options.init:  # read (and refused) before any work
        volume = init_volume(options.init, levels[0].grid if levels else fine, int(scene.images.shape[1]))
    rungs = [level.downscale for level in levels if level.downscale is not None]
    # the file is read on the coarsest rung; the hull is first carved on the first level's grid
    check_before_work(scene, options, fine, rungs[0] if rungs else None, levels[0].grid if levels else None)
    bound = check_workload(scene, options, fine, device, levels).bytes
    hook.begin()
    timing: dict = {}
    clock = time.perf_counter()
    scene, calibration = calibrated_scene(scene, options, device)
    if calibration is not None:
        timing["calibration"] = time.perf_counter() - clock
    options = with_capture_weights(options, calibration)
    capture_selection = (calibration or {}).get("selection") if not options.select.auto else None
    clock = time.perf_counter()
    volume = coarse_levels(scene, options, device, volume, first, hook, records)
    if levels:
        timing["coarse_levels"] = time.perf_counter() - clock
    final = options
    if options.ladder.final_iterations and any(level.downscale is not None for level in levels):
        final = options.replace(solver=options.solver.with_values(max_iters=options.ladder.final_iterations))
        log.info("ladder.final_iterations=%d: the run's own level solves %d iterations after the ladder's rungs, "
                 "not solver.max_iters=%s (give solver.max_iters on the command line and it holds there too)",
                 options.ladder.final_iterations, options.ladder.final_iterations,
                 options.solver.params.get("max_iters"))
    setup = build(scene, final, device, fine)
    timing.update(setup=setup.seconds, assembly=setup.assembly_seconds)
    x0 = None if volume is None else hull_values(volume, setup.grid, setup.voxel_index)
    del volume
    found = fit(setup, final, x0, hook, Stage(len(levels), len(levels)), {"level_records": list(records)})
    if capture_selection and found.selection is None:  # the capture's, chosen on its calibration frames
        found.selection = {**capture_selection, "source": f"the capture's calibration ({calibration.get('file')})"}
    timing.update(found.seconds)
    if levels:
        records.append(level_record(setup, found.l1, found.result))
    return Reconstruction(scene, setup, found, records, calibration, timing, bound)
