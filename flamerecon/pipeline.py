"""reconstruct(cfg): scene -> silhouettes -> visual hull -> operator -> solve -> outputs;
evaluate(run_dir): re-render a finished run's views and score them."""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from .atomic import write_json_atomic
from .cameras import K_of, camera_subset, cameras_to, make_cameras
from .checkpoint import CHECKPOINT_FILE, load_checkpoint
from .checks import (
    check_density_fits,
    check_grid_memory,
    check_scene,
    check_silhouettes,
    choose_backend,
    explain_empty_hull,
    memory_budget,
)
from .debias import DebiasOptions, debias
from .device import resolve_device
from .errors import ConfigError, Interrupted, ResumeError, RunFolderError, SolveDiverged
from .evaluation import native_scores, render_scene_views, score, score_views, write_renders
from .export import check_exporters, export_run, load_density, save_density
from .figures import top_view
from .grid import VoxelGrid
from .guard import SolveGuard, StopSolve, stop_signals
from .hull import hull_footprint, visual_hull
from .levels import level_grids, level_iters
from .metrics import resample_to
from .options_check import check_options
from .photometry import fit_gain_offset_rows, normalize_gains
from .projector import camera_rays, make_operator
from .refine_cameras import RefineOptions, correction_report, refine, with_cameras
from .run_lock import run_lock
from .scenes import Scene, load_scene
from .silhouettes import silhouettes
from .solvers import SOLVERS, Problem, Solver, SolveResult, make_solver, resolve_l1
from .tb_logging import RunWriter, side_by_side
from .weight_selection import SelectionOptions, select_weights

log = logging.getLogger(__name__)


@dataclass
class Setup:
    """Everything the solve needs, built once from the scene and the config."""

    scene: Scene
    train: list[int]
    holdout: list[int]
    grid: VoxelGrid
    masks: torch.Tensor  # (B, H, W) bool, every view
    hull: torch.Tensor  # (nz, ny, nx) bool
    voxel_index: torch.Tensor  # (M,) flat indices of hull voxels
    operator: object  # LinearOperator (N, M)
    pixels: torch.Tensor  # (N, C) training pixel values inside the silhouettes
    step: float
    row_view: torch.Tensor | None = None  # (N,) long: position in ``train`` of each pixel row
    seconds: float = 0.0  # wall time it took to build (hull, rays, operator)
    assembly_seconds: float = 0.0  # of which the operator (backend choice and assembly)

    def volume(self, x: torch.Tensor) -> torch.Tensor:
        """Hull values (M, C) -> dense density (C, nz, ny, nx)."""
        return self.grid.dense(x, self.voxel_index)


def scene_grid(cfg: DictConfig, scene: Scene) -> VoxelGrid:
    """The reconstruction grid: ``grid.bbox`` if set, else the scene's box."""
    bbox = cfg.grid.get("bbox")
    lo, hi = (bbox[0], bbox[1]) if bbox is not None else (scene.bbox_min, scene.bbox_max)
    res = cfg.grid.resolution
    res = int(res) if isinstance(res, (int, float)) else list(res)
    try:
        return VoxelGrid.from_box(lo, hi, res)
    except ValueError as err:
        raise ConfigError(f"grid: {err}") from err


def prepare(cfg: DictConfig, scene: Scene, device: torch.device, grid: VoxelGrid | None = None) -> Setup:
    """Split, silhouettes, visual hull, rays and the operator restricted to them, on ``grid``
    (default: the config's, :func:`scene_grid`)."""
    started = time.perf_counter()
    train, holdout = scene.split(OmegaConf.to_container(cfg.holdout) if cfg.holdout is not None else None)
    grid = grid if grid is not None else scene_grid(cfg, scene)
    check_scene(scene, grid)
    budget = memory_budget(device, cfg.projector.get("max_memory_gb"))
    check_grid_memory(grid, scene.num_views, device, budget)
    images = scene.images.to(device)
    masks = scene.masks.to(device) if scene.masks is not None else silhouettes(images, **cfg.silhouette)
    threshold = float(cfg.silhouette.get("threshold", 0.0))
    check_silhouettes(scene, masks, train, threshold)
    cams = cameras_to(camera_subset(scene.cameras, train), device)
    margin = int(cfg.hull.margin_voxels)
    hull = visual_hull(grid, cams, masks[train], margin)
    if not bool(hull.any()):
        raise explain_empty_hull(scene, grid, cams, masks[train], train, threshold, margin)
    voxel_index = hull.reshape(-1).nonzero().squeeze(1)
    rows = fit_pixels(cfg.projector.get("rays", "silhouette"), grid, cams, hull, masks[train])
    rays, flat = camera_rays(cams, rows)
    C = images.shape[1]
    pixels = images[train].permute(0, 2, 3, 1).reshape(-1, C)[flat].contiguous()
    row_view = flat // (images.shape[-2] * images.shape[-1])
    step = float(cfg.projector.step)
    assembly = time.perf_counter()
    backend = choose_backend(cfg.projector.backend, grid, rays, voxel_index, step, device, budget)
    operator = make_operator(backend, grid, rays, voxel_index, step)
    now = time.perf_counter()
    return Setup(scene, train, holdout, grid, masks, hull, voxel_index, operator, pixels, step, row_view,
                 now - started, now - assembly)


def fit_pixels(which: str, grid: VoxelGrid, cams, hull: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """The training pixels (T, H, W) bool whose rays enter the operator: ``silhouette``, the
    silhouette pixels only; ``hull``, also every background pixel whose ray can meet the hull
    (its zero is a constraint: no hull voxel is left unconstrained)."""
    if which == "silhouette":
        return masks
    if which == "hull":
        return masks | hull_footprint(grid, cams, hull)
    raise ConfigError(f"projector.rays: unknown value '{which}'; choose silhouette or hull")


def make_problem(cfg: DictConfig, setup: Setup) -> tuple[Problem, Solver, float]:
    """The solve of ``cfg`` on ``setup``: (problem, solver, absolute l1 weight)."""
    if cfg.solver.name not in SOLVERS:
        raise ConfigError(f"solver.name: unknown solver '{cfg.solver.name}'; choose one of {sorted(SOLVERS)}")
    l1, l1_rel = cfg.solver.get("l1"), cfg.solver.get("l1_rel")
    if l1 is not None:
        l1_rel = None  # an absolute weight wins over the relative default
    try:
        l1 = resolve_l1(setup.operator, setup.pixels, l1, l1_rel)
        solver = make_solver(cfg.solver.name, **solver_options(cfg))
    except ValueError as err:
        raise ConfigError(str(err)) from err
    problem = Problem(setup.operator, setup.pixels, l1, grid_shape=setup.grid.shape,
                      voxel_index=setup.voxel_index)
    return problem, solver, l1


@dataclass
class Photometry:
    """Per training camera ``image = gain * integral + offset`` (``gain``, ``offset``: (T,))."""

    gain: torch.Tensor
    offset: torch.Tensor
    iterations: list[int]  # of each re-solve

    def per_view(self, setup: Setup) -> dict[str, tuple[float, float]]:
        """{view name: (gain, offset)} for every view; held-out views get (1, 0)."""
        out = {name: (1.0, 0.0) for name in setup.scene.views}
        for k, v in enumerate(setup.train):
            out[setup.scene.views[v]] = (float(self.gain[k]), float(self.offset[k]))
        return out


def fit_photometry(cfg: DictConfig, setup: Setup, problem: Problem, solver: Solver,
                   result: SolveResult) -> tuple[SolveResult, Photometry | None]:
    """With ``photometry.fit_gain``: ``photometry.rounds`` times, fit each training camera's
    gain and offset to the current density's line integrals on its silhouette rows (gains
    normalized to geometric mean 1, so held-out cameras keep gain 1 and offset 0), then solve
    again from the current density on ``(pixels - offset) / gain``. Returns the last solve and
    the fitted photometry (None when off)."""
    opts = cfg.get("photometry") or {}
    if not opts.get("fit_gain", False):
        return result, None
    rounds = int(opts.get("rounds", 2))
    if rounds < 1:
        raise ConfigError(f"photometry.rounds: must be at least 1 when photometry.fit_gain is on, got {rounds}")
    T = len(setup.train)
    iterations, seconds = [], result.seconds
    gain = offset = None
    for _ in range(rounds):
        with torch.no_grad():
            predicted = setup.operator.forward(result.x)
        gain, offset = fit_gain_offset_rows(predicted, setup.pixels, setup.row_view, T,
                                            bool(opts.get("fit_offset", True)))
        if not bool((gain > 0).all()):
            bad = [setup.scene.views[setup.train[k]] for k in (gain <= 0).nonzero().flatten().tolist()]
            raise ConfigError(f"photometry.fit_gain: cameras {bad} got a gain <= 0 (their images do not "
                              "follow the density's line integrals); run with photometry.fit_gain=false")
        gain = normalize_gains(gain)
        b = (setup.pixels - offset[setup.row_view, None]) / gain[setup.row_view, None]
        again = Problem(setup.operator, b, problem.l1, grid_shape=problem.grid_shape,
                        voxel_index=problem.voxel_index)
        result = solver.solve(again, x0=result.x)
        iterations.append(result.iterations)
        seconds += result.seconds
    result.seconds = seconds
    return result, Photometry(gain.cpu(), offset.cpu(), iterations)


def debias_options(cfg: DictConfig) -> DebiasOptions:
    node = cfg.get("debias") or {}
    try:
        return DebiasOptions(str(node.get("method", "none")), int(node.get("iterations", 10)))
    except ValueError as err:
        raise ConfigError(str(err)) from err


def choose_weights(cfg: DictConfig, setup: Setup) -> tuple[DictConfig, dict | None]:
    """With ``select.auto`` and candidates for the run's solver (``select.candidates.<solver>``):
    the config with the solver weights that leave-one-view-out over the training views prefers
    (:func:`~flamerecon.weight_selection.select_weights`), and the selection's record for
    metrics.json; else ``cfg`` unchanged and None."""
    node = cfg.get("select") or {}
    table = node.get("candidates") or {}
    candidates = table.get(cfg.solver.name) if bool(node.get("auto", False)) else None
    candidates = OmegaConf.to_container(candidates, resolve=True) if candidates else []
    if not candidates:
        return cfg, None
    if cfg.solver.name not in SOLVERS:
        raise ConfigError(f"solver.name: unknown solver '{cfg.solver.name}'; choose one of {sorted(SOLVERS)}")
    try:
        options = SelectionOptions(tuple(dict(c) for c in candidates), int(node.get("folds", 4)),
                                   None if node.get("iterations") is None else int(node.iterations))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"select: {err}") from err
    if len(setup.train) < 2:
        raise ConfigError(f"select.auto: choosing weights needs at least two training views, "
                          f"got {len(setup.train)}; set select.auto=false")
    base = OmegaConf.to_container(cfg.solver, resolve=True)
    base.pop("name")
    images = setup.scene.images[setup.train].to(setup.pixels)
    energy = (images.double() ** 2).sum((-2, -1))  # (T, C)
    H, W = setup.scene.image_size
    try:
        found = select_weights(cfg.solver.name, base, options, debias_options(cfg), setup.operator,
                               setup.pixels, setup.row_view, energy, H * W,
                               [setup.scene.views[v] for v in setup.train],
                               {"grid_shape": setup.grid.shape, "voxel_index": setup.voxel_index})
    except (TypeError, ValueError) as err:  # a misspelt candidate key, as make_solver says it
        raise ConfigError(f"select.candidates.{cfg.solver.name}: {err}") from err
    log.info("weights chosen by leave-one-view-out over the training views: %s", found.chosen)
    return OmegaConf.merge(cfg, {"solver": found.chosen}), found.record()


def finish_solve(cfg: DictConfig, setup: Setup, result: SolveResult) -> tuple[SolveResult, dict]:
    """The ``debias`` step after the solve (and photometry): the result with the debiased
    density, and the record for metrics.json."""
    x, record = debias(debias_options(cfg), setup.operator, setup.pixels, result.x)
    result.x = x
    return result, record


def solve(cfg: DictConfig, setup: Setup, x0: torch.Tensor | None = None
          ) -> tuple[SolveResult, float, Photometry | None]:
    """Solve ``setup`` as ``cfg`` says, without a run folder (no callback, checkpoints or
    logging): weights chosen (``select``), solve, photometry, ``debias``; returns (result,
    absolute l1 weight, fitted photometry or None)."""
    cfg, _ = choose_weights(cfg, setup)
    problem, solver, l1 = make_problem(cfg, setup)
    result = solver.solve(problem, x0=x0)
    result, photometry = fit_photometry(cfg, setup, problem, solver, result)
    result, _ = finish_solve(cfg, setup, result)
    return result, l1, photometry


def init_volume(path: str | Path, grid: VoxelGrid, channels: int | None = None) -> torch.Tensor:
    """The density (C, nz', ny', nx') of a finished run (``init=``), which must cover the box of
    ``grid`` (its resolution may differ) and have ``channels`` channels (when given)."""
    try:
        saved = load_density(path)
    except FileNotFoundError as err:
        raise ConfigError(f"init: {err}; give a finished run's folder or its density.npz") from None
    if channels is not None and saved.density.shape[0] != channels:
        raise ConfigError(
            f"init: {path} holds {saved.density.shape[0]} channel(s), this run's images {channels}; "
            "warm start from a run of the same capture (scene.channels)"
        )
    if not (np.allclose(saved.bbox_min, grid.bbox_min) and np.allclose(saved.bbox_max, grid.bbox_max)):
        raise ConfigError(
            f"init: {path} covers the box {saved.bbox_min.tolist()}-{saved.bbox_max.tolist()}, "
            f"this run's grid {list(grid.bbox_min)}-{list(grid.bbox_max)}; warm start needs the same box"
        )
    return torch.from_numpy(saved.density)


def hull_values(volume: torch.Tensor, grid: VoxelGrid, voxel_index: torch.Tensor) -> torch.Tensor:
    """Hull values (M, C) of a density (C, nz', ny', nx') on the same box as ``grid``: its exact
    cell averages on ``grid`` (:func:`~flamerecon.metrics.resample_to`) read at ``voxel_index``.
    A warm start: cells the density is zero on (e.g. outside a coarser level's hull) start at 0."""
    vol = resample_to(volume, grid.shape).to(voxel_index.device)
    return vol.reshape(vol.shape[0], -1)[:, voxel_index].T.contiguous()


def level_config(cfg: DictConfig, max_iters: int | None, cell_ratio: float) -> DictConfig:
    """``cfg`` for a coarse level: ``solver.max_iters`` set to its budget (unchanged for None);
    an absolute ``solver.l1`` (the final grid's) times ``cell_ratio``, the level's cell volume
    over the final grid's, the weight under which the coarse problem is the final one restricted
    to densities constant on the coarse cells (``solver.l1_rel`` needs nothing: max(A^T P) of
    each level scales the same way)."""
    change: dict = {}
    if max_iters is not None:
        change["max_iters"] = max_iters
    if cfg.solver.get("l1"):
        change["l1"] = float(cfg.solver.l1) * cell_ratio
    return OmegaConf.merge(cfg, {"solver": change}) if change else cfg


LevelSolve = Callable[[int, DictConfig, Setup, "torch.Tensor | None"], SolveResult]


def plain_level_solve(level: int, cfg: DictConfig, setup: Setup, x0: torch.Tensor | None) -> SolveResult:
    """A coarse level's solve without a run folder (no callback, photometry or checkpoints)."""
    problem, solver, _ = make_problem(cfg, setup)
    return solver.solve(problem, x0=x0)


def coarse_levels(cfg: DictConfig, scene: Scene, device: torch.device, volume: torch.Tensor | None = None,
                  first: int = 0, solve_level: LevelSolve = plain_level_solve) -> torch.Tensor | None:
    """Solve the coarse grids of ``grid.levels`` from ``first`` on, coarsest first, each on its
    own visual hull and operator (same box, silhouettes and solver config, see
    :func:`level_config` for its L1 weight and iteration budget), each
    starting from the previous density resampled onto it (the first from ``volume``, or 0).
    Returns the last level's density (C, nz, ny, nx), or ``volume`` when there are no levels."""
    fine = scene_grid(cfg, scene)
    grids = level_grids(cfg.grid.get("levels"), fine)
    budgets = level_iters(cfg.grid.get("level_iters"), len(grids))
    for level in range(first, len(grids)):
        level_cfg = level_config(cfg, budgets[level], fine.num_voxels / grids[level].num_voxels)
        setup = prepare(level_cfg, scene, device, grids[level])
        x0 = None if volume is None else hull_values(volume, setup.grid, setup.voxel_index)
        result = solve_level(level, level_cfg, setup, x0)
        volume = setup.volume(result.x)
        del setup, result  # free this level's operator before the next is built
    return volume


def warm_start(cfg: DictConfig, scene: Scene, device: torch.device, setup: Setup) -> torch.Tensor | None:
    """x0 (M, C) for the fine ``setup`` without a run folder: the ``init=`` run's density
    and/or the solutions of ``grid.levels`` (see :func:`coarse_levels`); None for a cold start."""
    grids = level_grids(cfg.grid.get("levels"), setup.grid)
    volume = (init_volume(cfg.init, grids[0] if grids else setup.grid, setup.pixels.shape[1])
              if cfg.get("init") else None)
    volume = coarse_levels(cfg, scene, device, volume)
    return None if volume is None else hull_values(volume, setup.grid, setup.voxel_index)


def refine_options(cfg: DictConfig) -> RefineOptions:
    """The ``calibration:`` node as :class:`~flamerecon.refine_cameras.RefineOptions`."""
    node = OmegaConf.to_container(cfg.get("calibration") or {}, resolve=True)
    try:
        return RefineOptions(**node)
    except TypeError as err:
        raise ConfigError(f"calibration: {err}; valid keys are {list(RefineOptions.__dataclass_fields__)}") from err
    except ValueError as err:
        raise ConfigError(str(err)) from err


def calibrated_scene(cfg: DictConfig, scene: Scene, device: torch.device) -> tuple[Scene, dict | None]:
    """With ``calibration.refine`` other than ``none``: ``scene`` with its training cameras
    refined through the renderer (:func:`~flamerecon.refine_cameras.refine`, each density
    solve as :func:`prepare` and :func:`solve` do it, on the final grid), its held-out cameras
    unchanged, and the record for metrics.json's ``calibration`` (corrections per camera, the
    scores of the density solved before refinement). ``(scene, None)`` when off."""
    options = refine_options(cfg)
    if options.refine == "none":
        return scene, None
    started = time.perf_counter()
    train, holdout = scene.split(OmegaConf.to_container(cfg.holdout) if cfg.holdout is not None else None)
    grid = scene_grid(cfg, scene)
    images = scene.images.to(device)
    masks = scene.masks.to(device) if scene.masks is not None else silhouettes(images, **cfg.silhouette)
    step = float(cfg.projector.step)

    def solve_density(views: list[int], cameras) -> torch.Tensor:
        fold = cfg.copy()
        fold.holdout = [name for i, name in enumerate(scene.views) if i not in views]
        setup = prepare(fold, replace(scene, cameras=with_cameras(scene.cameras, views, cameras)), device, grid)
        result, _, _ = solve(fold, setup)
        return setup.volume(result.x)

    found = refine(cameras_to(scene.cameras, device), train, images, masks, grid, solve_density, options, step)
    refined = replace(scene, cameras=cameras_to(found.cameras, "cpu"),
                      meta={**scene.meta, "calibrated_cameras": scene.cameras})
    silhouette = OmegaConf.to_container(cfg.silhouette, resolve=True)
    before, _ = score(scene, found.initial_volume, grid, train, holdout, step, silhouette)
    report = correction_report(camera_subset(scene.cameras, train), camera_subset(refined.cameras, train),
                               grid, found.corrections.cpu())
    record = {
        "refine": options.refine, "rounds": found.history, "seconds": time.perf_counter() - started,
        "train_psnr_before": mean_of(before["train"], "psnr"),
        "heldout_psnr_before": mean_of(before["heldout"], "psnr"),
        "cameras": {scene.views[v]: r for v, r in zip(train, report)},
    }
    return refined, record


def cameras_record(scene: Scene, train: list[int],
                   photometry: dict[str, tuple[float, float]] | None = None) -> list[dict]:
    """cameras.json content: every camera with K, world_to_camera, size, its role, and its
    ``gain`` and ``offset`` (image = gain * integral + offset; 1 and 0 unless fitted); after
    calibration refinement K and world_to_camera are the refined ones and ``K_calibrated``,
    ``world_to_camera_calibrated`` the scene's own."""
    K = K_of(scene.cameras).cpu()
    E = scene.cameras.extrinsics.cpu()
    photometry = photometry or {}
    original = scene.meta.get("calibrated_cameras")
    records = [
        {
            "name": name,
            "K": K[i].tolist(),
            "world_to_camera": E[i].tolist(),
            "width": int(scene.cameras.width[i]),
            "height": int(scene.cameras.height[i]),
            "split": "train" if i in train else "holdout",
            "gain": photometry.get(name, (1.0, 0.0))[0],
            "offset": photometry.get(name, (1.0, 0.0))[1],
        }
        for i, name in enumerate(scene.views)
    ]
    if original is not None:
        for i, record in enumerate(records):
            record["K_calibrated"] = K_of(original)[i].cpu().tolist()
            record["world_to_camera_calibrated"] = original.extrinsics[i].cpu().tolist()
    return records


def mean_of(per_view: dict[str, dict[str, float]], key: str) -> float:
    vals = [v[key] for v in per_view.values()]
    return sum(vals) / len(vals) if vals else math.nan


def summary_table(metrics: dict) -> str:
    """The short table printed at the end of a run."""
    s = metrics["solver"]
    rows = [
        ("held-out PSNR [dB]", (f"{mean_of(metrics['heldout'], 'psnr'):.2f}  (black image: "
                               f"{mean_of(metrics['heldout'], 'psnr_black'):.2f})")),
        ("held-out SSIM", f"{mean_of(metrics['heldout'], 'ssim'):.4f}"),
        ("  appearance-aligned [dB]", (f"{mean_of(metrics['heldout'], 'psnr_aligned'):.2f}  "
                                      "(gain fitted on the left half, PSNR of the right half)")),
    ]
    held = list(metrics["heldout"].values())
    if held and "psnr_silhouette" in held[0]:
        rows.append(("  inside silhouettes [dB]", (
            f"{mean_of(metrics['heldout'], 'psnr_silhouette'):.2f}  "
            f"(black image: {mean_of(metrics['heldout'], 'psnr_black_silhouette'):.2f})")))
    if held and "psnr_native" in held[0]:
        W, H = metrics["resolution"]["native"]
        rows += [
            (f"  native {W}x{H} PSNR [dB]", (
                f"{mean_of(metrics['heldout'], 'psnr_native'):.2f}  "
                f"(black image: {mean_of(metrics['heldout'], 'psnr_black_native'):.2f})")),
            (f"  native {W}x{H} SSIM", f"{mean_of(metrics['heldout'], 'ssim_native'):.4f}"),
        ]
    rows.append(("training PSNR [dB]", f"{mean_of(metrics['train'], 'psnr'):.2f}"))
    c = metrics.get("calibration")
    if c:
        rows.append((f"calibration ({c['refine']})", (
            f"training {c['train_psnr_before']:.2f} -> {c['train_psnr_after']:.2f} dB, "
            f"held-out before refinement {c['heldout_psnr_before']:.2f} dB")))
        rows += [(f"  {name}", (f"{r['rotation_deg']:.3f} deg, {r['translation']:.4g} world units, "
                                f"focal x{r['focal_scale']:.4f}, principal point "
                                f"({r['principal_point_px'][0]:+.2f}, {r['principal_point_px'][1]:+.2f}) px, "
                                f"box moves {r['box_px']:.2f} px"))
                 for name, r in c["cameras"].items()]
    if "volume" in metrics:
        rows.append(("volume rel. L2 / IoU", f"{metrics['volume']['rel_l2']:.4f} / {metrics['volume']['iou']:.4f}"))
    rows += [
        ("solver", f"{s['name']} (l1 = {s['l1']:.4g})"),
        ("iterations", f"{s['iterations']}" + (
            "" if s.get("converged", True) else " (stopped by the budget"
            + (f"; relative duality gap {s['rel_gap']:.1e})" if "rel_gap" in s else ")"))),
        ("seconds", f"{s['seconds']:.2f}"),
    ]
    if "timing" in metrics:
        rows.append(("time split [s]", time_split(metrics["timing"])))
    if "levels" in s:
        rows.append(("grid levels", "; ".join(
            f"{cells_of(r['resolution'])}: {r['iterations']} it, "
            f"{r['setup_seconds']:.2f} s setup + {r['seconds']:.2f} s solve"
            for r in s["levels"])))
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


def time_split(timing: dict[str, float]) -> str:
    """metrics.json's ``timing`` as one line, e.g. ``scene 0.4, setup 1.2 (assembly 0.8), ...``."""
    parts = [f"{k.replace('_', ' ')} {v:.2f}" + (f" (assembly {timing['assembly']:.2f})" if k == "setup" else "")
             for k, v in timing.items() if k != "assembly"]
    return ", ".join(parts)


class Monitor:
    """Solver callback: progress bar, TensorBoard scalars, held-out PSNR and pictures. Tags
    start with ``tag_root`` (``""`` for the final grid, ``level<i>/`` for coarse level i).

    The held-out views are rendered at most every ``log.eval_every`` iterations and only while
    the monitor's own wall time, this render included (predicted from the last one), stays
    within ``log.eval_share`` of the solve's (null: no limit), so that past the first render
    they cost at most that share. :attr:`seconds` is the wall time spent here.
    """

    def __init__(self, setup: Setup, writer: RunWriter, cfg: DictConfig, total: int, device,
                 tag_root: str = ""):
        self.setup, self.writer, self.cfg = setup, writer, cfg
        desc = "solve" if not tag_root else f"solve {tag_root.rstrip('/')}"
        self.bar = tqdm(total=total, desc=desc, unit="it", leave=False, dynamic_ncols=True)
        self.device = device
        self.tag_root = tag_root
        self.last = 0
        self.started = time.perf_counter()
        self.seconds = 0.0
        self.render_seconds = 0.0  # the last render's cost: the next one's prediction
        self.last_pictures = 0

    def __call__(self, it: int, x: torch.Tensor, info: dict) -> None:
        now = time.perf_counter()
        self.bar.update(it - self.last)
        self.last = it
        self.bar.set_postfix(objective=f"{info['objective']:.4g}", gap=f"{info.get('rel_gap', math.nan):.1e}")
        values = {k: info[k] for k in ("objective", "data", "l1", "smooth", "tv", "rel_gap") if k in info}
        values["nonzero_fraction"] = float((x > 0).any(1).float().mean())
        self.writer.scalars(it, values, prefix=f"{self.tag_root}solve")
        every = int(self.cfg.log.eval_every)
        share = self.cfg.log.get("eval_share", 0.1)
        affordable = share is None or (
            self.seconds + self.render_seconds <= float(share) * (now - self.started))
        if every > 0 and it - self.last_pictures >= every and affordable:
            start = time.perf_counter()
            self.pictures(it, x)
            self.render_seconds = time.perf_counter() - start
            self.last_pictures = it
        self.seconds += time.perf_counter() - now

    def pictures(self, it: int, x: torch.Tensor) -> None:
        """Render the held-out views of the iterate x (M, C) and log them."""
        s = self.setup
        vol = s.volume(x.detach())
        self.log_pictures(it, vol, render_scene_views(vol, s.grid, s.scene, s.holdout, s.step))

    def log_pictures(self, it: int, vol: torch.Tensor, imgs: torch.Tensor) -> None:
        """Held-out PSNR, held-out renders imgs (V, C, H, W) beside the captured views, and the
        top view of vol (C, nz, ny, nx), at step ``it``."""
        s, root = self.setup, self.tag_root
        scores = score_views(imgs, s.scene, s.holdout)
        self.writer.scalars(it, {"heldout_psnr": mean_of(scores, "psnr")}, prefix=f"{root}eval")
        for img, v in zip(imgs, s.holdout):
            self.writer.image(f"{root}heldout/{s.scene.views[v]}", side_by_side(img, s.scene.images[v]), it)
        self.writer.image(f"{root}density/top_view", top_view(vol, s.grid.bbox_min, s.grid.bbox_max),
                          it, "HWC")

    def close(self) -> None:
        self.bar.close()


def solver_options(cfg: DictConfig) -> dict:
    opts = OmegaConf.to_container(cfg.solver, resolve=True)
    for k in ("name", "l1", "l1_rel"):
        opts.pop(k, None)
    return opts


def reconstruct(cfg: DictConfig, run_dir: str | Path, resume: bool = False) -> dict:
    """:func:`reconstruct_in` after checking every option of ``cfg``
    (:func:`~flamerecon.options_check.check_options`), holding ``run_dir``'s lock
    (:func:`~flamerecon.run_lock.run_lock`: a second writer is refused)."""
    check_options(OmegaConf.to_container(cfg, resolve=True))
    check_exporters(cfg.get("export", {}).get("formats", []))
    with run_lock(run_dir):
        return reconstruct_in(cfg, run_dir, resume)


def start_run(cfg: DictConfig, run_dir: str | Path) -> tuple[Path, torch.device]:
    """What every reconstruction does first: the run folder made, the seed and thread count
    set, the device resolved."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(cfg.seed))
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    return run_dir, resolve_device(cfg.device)


def reconstruct_in(cfg: DictConfig, run_dir: str | Path, resume: bool = False) -> dict:
    """Run the whole pipeline for ``cfg`` and write the run folder; returns metrics.json's dict.

    With ``grid.levels`` the coarse grids are solved first (:func:`coarse_levels`), each logged
    to TensorBoard under the tag prefix ``level<i>/`` and recorded in metrics.json's
    ``solver.levels``; the final grid logs under the usual tags. With ``resume`` the solve
    continues from ``run_dir/checkpoint.pt``, at the level it was written on. Raises
    :class:`~flamerecon.errors.Interrupted` after checkpointing on SIGINT/SIGTERM, and
    :class:`~flamerecon.errors.SolveDiverged` after writing the last good iterate's outputs
    (a coarse level that diverges writes none).
    """
    if cfg.scene.get("frames") is not None:  # consecutive frames solved jointly (time as a prior)
        from .temporal_run import reconstruct_frames

        return reconstruct_frames(cfg, run_dir, resume)
    run_dir, device = start_run(cfg, run_dir)
    if cfg.solver.name not in SOLVERS:
        raise ConfigError(f"solver.name: unknown solver '{cfg.solver.name}'; choose one of {sorted(SOLVERS)}")
    ckpt = load_checkpoint(run_dir) if resume else None
    clock = time.perf_counter()
    scene, calibration = calibrated_scene(cfg, load_scene(cfg.scene), device)
    timing = {"scene": time.perf_counter() - clock}
    fine = scene_grid(cfg, scene)
    grids = level_grids(cfg.grid.get("levels"), fine)
    level_iters(cfg.grid.get("level_iters"), len(grids))  # refuse a bad budget before any solve
    plan = [list(g.resolution) for g in grids]
    final = len(grids)
    # a checkpoint without "level" predates grid.levels: it is the final grid's
    at = final if ckpt is None else int(ckpt["meta"].get("level", final))
    records: list[dict] = [] if ckpt is None else list(ckpt["meta"].get("level_records", []))
    if ckpt is not None and ckpt["meta"].get("levels", plan) != plan:
        raise ResumeError(
            f"{run_dir / CHECKPOINT_FILE}: field 'levels' is {ckpt['meta']['levels']} but the run's config "
            f"now gives grid.levels as {plan}; resume with the grid.levels it was started with"
        )
    volume = None
    if ckpt is None and cfg.get("init"):
        volume = init_volume(cfg.init, grids[0] if grids else fine, int(scene.images.shape[1]))

    def solve_level(level: int, level_cfg: DictConfig, setup: Setup, x0: torch.Tensor | None) -> SolveResult:
        """Coarse level ``level`` under the watchdog, resumed when the checkpoint is its own."""
        problem, solver, l1 = make_problem(level_cfg, setup)
        meta = problem_meta(level_cfg, setup, l1, level, plan)
        here = ckpt if ckpt is not None and level == at else None
        if here is None and x0 is not None:  # TensorBoard shows where the warm start begins
            writer.scalars(0, {"objective": problem.objective(x0)}, prefix=f"level{level}/solve")
        result, stopped, _ = guarded_solve(level_cfg, run_dir, setup, problem, solver, writer, device,
                                           meta, x0, here, level, {"level_records": records})
        if stopped is not None:
            raise SolveDiverged(
                f"{run_dir}: the solve on coarse level grid.levels[{level}] ({cells(setup.grid)} cells) "
                f"{stopped}; nothing was written; try a smaller step (solver.lr), another solver, "
                "or other grid.levels"
            )
        records.append(level_record(setup, l1, result))
        return result

    writer = RunWriter(str(run_dir))
    try:
        clock = time.perf_counter()
        volume = coarse_levels(cfg, scene, device, volume, 0 if ckpt is None else at, solve_level)
        if grids:
            timing["coarse_levels"] = time.perf_counter() - clock
        setup = prepare(cfg, scene, device, fine)
        timing.update(setup=setup.seconds, assembly=setup.assembly_seconds)
        clock = time.perf_counter()
        cfg, selection = choose_weights(cfg, setup)
        if selection is not None:
            timing["selection"] = time.perf_counter() - clock
        problem, solver, l1 = make_problem(cfg, setup)
        meta = problem_meta(cfg, setup, l1, final, plan)
        here = ckpt if ckpt is not None and at == final else None
        x0 = None
        if here is None and volume is not None:
            x0 = hull_values(volume, setup.grid, setup.voxel_index)
            if grids:  # TensorBoard shows where the coarse levels left the fine problem
                writer.scalars(0, {"objective": problem.objective(x0)})
        del volume
        clock = time.perf_counter()
        result, stopped, monitor = guarded_solve(cfg, run_dir, setup, problem, solver, writer, device,
                                                 meta, x0, here, final, {"level_records": records})
        timing.update(solve=time.perf_counter() - clock - monitor.seconds, monitoring=monitor.seconds)
        photometry, debiased = None, None
        if stopped is None:
            clock = time.perf_counter()
            result, photometry = fit_photometry(cfg, setup, problem, solver, result)
            if photometry is not None:
                timing["photometry"] = time.perf_counter() - clock
            result, debiased = finish_solve(cfg, setup, result)
        if grids:
            records.append(level_record(setup, l1, result))
        clock = time.perf_counter()
        metrics = write_outputs(cfg, run_dir, scene, setup, writer, monitor, result, l1, stopped,
                                photometry, records,
                                {"selection": selection, "debias": debiased}, calibration)
        timing["outputs"] = time.perf_counter() - clock
    finally:
        writer.close()
    if stopped is not None:
        raise SolveDiverged(
            f"{run_dir}: the solve {stopped}; density.npz and metrics.json hold the last good "
            f"iterate (iteration {result.iterations}); try a smaller step (solver.lr) or another solver"
        )
    (run_dir / CHECKPOINT_FILE).unlink(missing_ok=True)  # finished: nothing left to resume
    formats = cfg.get("export", {}).get("formats", [])
    if formats:
        clock = time.perf_counter()
        export_run(run_dir, list(formats))
        timing["export"] = time.perf_counter() - clock
    metrics["timing"] = {**timing, "total": sum(v for k, v in timing.items() if k != "assembly")}
    write_json_atomic(run_dir / "metrics.json", metrics)
    return metrics


def cells_of(resolution) -> str:
    """``nx x ny x nz`` of a resolution (nx, ny, nz), for messages."""
    return "x".join(str(n) for n in resolution)


def cells(grid: VoxelGrid) -> str:
    """``nx x ny x nz`` of a grid, for messages."""
    return cells_of(grid.resolution)


def problem_meta(cfg: DictConfig, setup: Setup, l1: float, level: int, plan: list[list[int]]) -> dict:
    """What identifies a solve for resuming: solver, operator shape, channels, absolute l1,
    the grid level (``len(plan)``: the final grid) and the coarse grids of ``grid.levels``."""
    return {"solver": cfg.solver.name, "shape": list(setup.operator.shape),
            "channels": int(setup.pixels.shape[1]), "l1": l1, "level": level, "levels": plan}


def level_record(setup: Setup, l1: float, result: SolveResult) -> dict:
    """One grid level's entry in metrics.json's ``solver.levels``."""
    return {"resolution": list(setup.grid.resolution), "voxels": int(setup.voxel_index.numel()),
            "l1": l1, "iterations": result.iterations, "seconds": result.seconds,
            "setup_seconds": setup.seconds, "objective": result.objective,
            "converged": result.converged}


def guarded_solve(cfg: DictConfig, run_dir: Path, setup: Setup, problem: Problem, solver: Solver,
                  writer: RunWriter, device: torch.device, meta: dict, x0: torch.Tensor | None,
                  ckpt: dict | None, level: int, extra: dict
                  ) -> tuple[SolveResult, StopSolve | None, Monitor]:
    """Solve ``problem`` under the run's watchdog (:class:`~flamerecon.guard.SolveGuard`):
    TensorBoard monitor (tags under ``level<level>/`` for a coarse level), checkpoints holding
    ``meta`` and ``extra``, stop on divergence, :class:`~flamerecon.errors.Interrupted` after a
    checkpoint on SIGINT/SIGTERM. With ``ckpt`` it continues from that checkpoint instead of
    ``x0``. Returns (result, the divergence stop or None, the monitor)."""
    final = level == len(meta["levels"])
    start, seconds_before = 0, 0.0
    if ckpt is not None:
        x0, start, seconds_before = resume_solver(run_dir, ckpt, solver, meta)
    start_x = x0 if x0 is not None else setup.pixels.new_zeros(problem.A.shape[1], problem.b.shape[1])
    start_objective = float(problem.objective(setup.pixels.new_zeros(start_x.shape)))
    monitor = Monitor(setup, writer, cfg, int(cfg.solver.get("max_iters") or 0), device,
                      "" if final else f"level{level}/")
    monitor.last = monitor.last_pictures = start
    ck = cfg.get("checkpoint") or {}
    guard = SolveGuard(solver, monitor, run_dir, int(ck.get("every", 0)),
                       float(ck.get("divergence_factor", 0.0)), start_objective, {**meta, **extra},
                       (start, start_x), seconds_before)
    stopped: StopSolve | None = None
    try:
        with stop_signals() as signals:
            guard.signals = signals
            try:
                result = solver.solve(problem, x0=x0, callback=guard)
                result.seconds = guard.seconds()
            except StopSolve as stop:
                if stop.reason == "interrupted":
                    where = "" if final else f" of coarse level grid.levels[{level}] ({cells(setup.grid)} cells)"
                    raise Interrupted(
                        f"{run_dir}: {stop.detail} at iteration {stop.iteration}{where}; the state is saved "
                        f"in {CHECKPOINT_FILE}; continue with: python train.py resume={run_dir}"
                    ) from None
                stopped = stop
                it, x = guard.last_good
                log.error("solve %s; keeping the last good iterate (iteration %d)", stop, it)
                result = SolveResult(x, it, guard.seconds(), problem.objective(x), False)
    finally:
        monitor.close()
    return result, stopped, monitor


def resume_solver(run_dir: Path, ckpt: dict, solver, meta: dict) -> tuple[torch.Tensor, int, float]:
    """Load checkpoint ``ckpt`` of ``run_dir`` into ``solver``; returns (x0, iteration, seconds
    so far). Refuses a checkpoint made for another problem (solver, operator shape, channels, l1)."""
    saved = ckpt["meta"]
    for key, now in meta.items():
        if key in saved and saved[key] != now:
            raise ResumeError(
                f"{run_dir / CHECKPOINT_FILE}: field '{key}' is {saved[key]} but the run's config now "
                f"gives {now}; the scene, grid or solver changed since the checkpoint"
            )
    state = ckpt["state"]
    if ckpt.get("exact"):
        solver.load_state(state)
    else:
        log.warning("%s: solver %s cannot restore its internal state; resuming from the saved "
                    "iterate (a warm start, not bit-identical to an uninterrupted run)",
                    run_dir / CHECKPOINT_FILE, meta["solver"])
    log.info("resuming %s from iteration %d", run_dir, state["iteration"])
    return state["x"], int(state["iteration"]), float(saved.get("seconds", 0.0))


def write_outputs(cfg: DictConfig, run_dir: Path, scene: Scene, setup: Setup, writer: RunWriter,
                  monitor: Monitor, result: SolveResult, l1: float, stopped: StopSolve | None,
                  photometry: Photometry | None = None, levels: list[dict] | None = None,
                  steps: dict | None = None, calibration: dict | None = None) -> dict:
    """density.npz, cameras.json, metrics.json, renders/ and the final TensorBoard entries;
    ``levels``: one :func:`level_record` per grid, coarsest first (only with ``grid.levels``);
    ``steps``: the records of the weight selection and the debiasing (None where off);
    ``calibration``: the record of :func:`calibrated_scene` (with calibration refinement)."""
    volume = setup.volume(result.x)
    solver_info = {
        "name": cfg.solver.name, "l1": l1, "iterations": result.iterations,
        "seconds": result.seconds, "objective": result.objective, "converged": result.converged,
        "status": "finished" if stopped is None else "diverged", "device": str(result.x.device),
    }
    gaps = [h["rel_gap"] for h in result.history if "rel_gap" in h]
    if gaps:
        solver_info["rel_gap"] = gaps[-1]
    if stopped is not None:
        solver_info["stopped"] = {"iteration": stopped.iteration, "reason": stopped.detail}
    if levels:
        solver_info["levels"] = levels
    solver_info.update({k: v for k, v in (steps or {}).items() if v is not None})
    per_view = None
    if photometry is not None:
        solver_info["photometry"] = {"rounds": len(photometry.iterations), "iterations": photometry.iterations}
        per_view = photometry.per_view(setup)
    train_names = [scene.views[i] for i in setup.train]
    save_density(
        run_dir / "density.npz", volume.cpu(), setup.grid.bbox_min, setup.grid.bbox_max,
        train_names, solver=json.dumps(solver_info), frame=int(cfg.scene.get("frame", 0)),
    )
    write_json_atomic(run_dir / "cameras.json", {"cameras": cameras_record(scene, setup.train, per_view)})
    metrics, held_imgs = finish(cfg, run_dir, scene, volume, setup.grid, setup.train, setup.holdout,
                                setup.step, solver_info, per_view, calibration=calibration)
    for name, values in (calibration or {}).get("cameras", {}).items():
        writer.scalars(0, {k: v for k, v in values.items() if k != "principal_point_px"}, f"calibration/{name}")
    if calibration:
        writer.scalars(0, {k: metrics["calibration"][k] for k in ("train_psnr_before", "train_psnr_after")},
                       "calibration")
    monitor.log_pictures(result.iterations, volume, held_imgs)  # the final renders, not again
    writer.image("images/hull_top_view", top_view(setup.hull[None].float(), setup.grid.bbox_min,
                                                  setup.grid.bbox_max), 0, "HWC")
    writer.hparams(
        {"scene": cfg.scene.name, "solver": cfg.solver.name, "l1": l1,
         "grid": str(setup.grid.resolution),
         "grid_levels": str(list(cfg.grid.get("levels") or [])),
         "holdout": ",".join(scene.views[i] for i in setup.holdout),
         **{k: float(cfg.solver[k]) for k in ("smooth", "tv") if cfg.solver.get(k) is not None}},
        flat_metrics(metrics),
    )
    return metrics


def flat_metrics(metrics: dict) -> dict[str, float]:
    out = {
        "heldout_psnr": mean_of(metrics["heldout"], "psnr"),
        "heldout_ssim": mean_of(metrics["heldout"], "ssim"),
        "train_psnr": mean_of(metrics["train"], "psnr"),
        "seconds": metrics["solver"]["seconds"],
    }
    if "volume" in metrics:
        out.update({f"volume_{k}": v for k, v in metrics["volume"].items()})
    return out


def finish(cfg: DictConfig, run_dir: Path, scene: Scene, volume: torch.Tensor, grid: VoxelGrid,
           train: list[int], holdout: list[int], step: float, solver_info: dict,
           photometry: dict[str, tuple[float, float]] | None = None,
           native: bool = False, calibration: dict | None = None) -> tuple[dict, torch.Tensor]:
    """Score, write renders/ and metrics.json; returns the metrics and the held-out renders
    (V, C, H, W). With ``native`` the held-out views are also scored at the capture's native
    resolution (when the run works below it). ``calibration`` (see :func:`calibrated_scene`)
    goes to metrics.json with ``train_psnr_after``, this density's training PSNR."""
    silhouette = OmegaConf.to_container(cfg.silhouette, resolve=True)
    metrics, held_imgs = score(scene, volume, grid, train, holdout, step, silhouette, photometry)
    H, W = scene.image_size
    metrics["resolution"] = {"working": [W, H]}
    if native:
        found = native_scores(cfg.scene, volume, grid, [scene.views[v] for v in holdout], step)
        if found is not None:
            per_view, size = found
            for name, values in per_view.items():
                metrics["heldout"][name].update(values)
            metrics["resolution"]["native"] = list(size)
    metrics["solver"] = solver_info
    if calibration:
        metrics["calibration"] = {**calibration, "train_psnr_after": mean_of(metrics["train"], "psnr")}
    write_renders(run_dir, held_imgs, scene, holdout)
    write_json_atomic(run_dir / "metrics.json", metrics)
    return metrics, held_imgs


def run_config(run_dir: str | Path) -> DictConfig:
    """The config a run folder was made with (``.hydra/config.yaml``)."""
    cfg_path = Path(run_dir) / ".hydra" / "config.yaml"
    if not cfg_path.is_file():
        raise RunFolderError(f"{cfg_path}: not found; is {run_dir} a flamerecon run folder?")
    return OmegaConf.load(cfg_path)


def read_photometry(run_dir: Path) -> dict[str, tuple[float, float]] | None:
    """{view: (gain, offset)} from a run's cameras.json, None when it has none."""
    path = run_dir / "cameras.json"
    if not path.is_file():
        return None
    cams = json.loads(path.read_text()).get("cameras", [])
    return {c["name"]: (float(c.get("gain", 1.0)), float(c.get("offset", 0.0))) for c in cams}


def recorded_calibration(run_dir: Path, scene: Scene) -> tuple[Scene, dict | None]:
    """``scene`` with the refined cameras of a run that refined its calibration (cameras.json's
    K and world_to_camera where it also holds ``K_calibrated``), and metrics.json's
    ``calibration`` record; ``(scene, None)`` for a run without refinement."""
    path = run_dir / "cameras.json"
    cams = json.loads(path.read_text()).get("cameras", []) if path.is_file() else []
    if not cams or "K_calibrated" not in cams[0]:
        return scene, None
    by_name = {c["name"]: c for c in cams}
    missing = [v for v in scene.views if v not in by_name]
    if missing:
        raise RunFolderError(f"{path}: no camera named {missing}; the scene has {scene.views}")
    K = torch.tensor([by_name[v]["K"] for v in scene.views])
    E = torch.tensor([by_name[v]["world_to_camera"] for v in scene.views])
    cameras = make_cameras(K, E, scene.cameras.height, scene.cameras.width)
    old = run_dir / "metrics.json"
    record = json.loads(old.read_text()).get("calibration") if old.is_file() else None
    return replace(scene, cameras=cameras, meta={**scene.meta, "calibrated_cameras": scene.cameras}), record


def evaluate(run_dir: str | Path, device: str = "auto", native: bool = True) -> dict:
    """Re-render the views of a finished run from its saved ``density.npz`` and config,
    write ``metrics.json`` and ``renders/``; returns the metrics. With ``native`` the held-out
    views are also scored at the capture's native resolution (``scene.downscale=1``)."""
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    saved = load_density(run_dir / "density.npz")
    scene, calibration = recorded_calibration(run_dir, load_scene(cfg.scene))
    train, holdout = scene.split(OmegaConf.to_container(cfg.holdout) if cfg.holdout is not None else None)
    lo, hi = tuple(saved.bbox_min.tolist()), tuple(saved.bbox_max.tolist())
    nz, ny, nx = saved.density.shape[1:]
    grid = VoxelGrid(lo, hi, (nx, ny, nz))
    check_density_fits(run_dir / "density.npz", saved, scene, scene_grid(cfg, scene),
                       run_dir / ".hydra" / "config.yaml")
    volume = torch.from_numpy(saved.density).to(resolve_device(device))
    with np.load(run_dir / "density.npz") as f:
        solver_info = json.loads(str(f["solver"])) if "solver" in f.files else {}
    metrics, _ = finish(cfg, run_dir, scene, volume, grid, train, holdout, float(cfg.projector.step),
                        solver_info, read_photometry(run_dir), native, calibration)
    return metrics
