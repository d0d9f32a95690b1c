"""build(scene, options): the discrete problem of a reconstruction — split, silhouettes, visual
hull, rays and the operator restricted to them — and the solver that fits it."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flamerecon.arguments import fields, instance, tensor, value, wrong_type, wrong_value
from flamerecon.device import resolve_device, set_threads
from flamerecon.errors import ConfigError, FlameReconError
from flamerecon.evaluate.metrics import resample_to
from flamerecon.fit.capture_operator import capture_operator
from flamerecon.fit.checks import (
    check_grid_memory,
    check_scene,
    check_silhouettes,
    choose_backend,
    density_fault,
    explain_empty_hull,
    memory_budget,
)
from flamerecon.fit.options import GridOptions, ReconstructionOptions, SolverOptions
from flamerecon.geometry.cameras import camera_subset, cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import hull_footprint, visual_hull
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.operators.projector import camera_rays, make_operator
from flamerecon.outputs.export import density_path, load_density
from flamerecon.rules import integer, list_of, number
from flamerecon.scenes import Scene
from flamerecon.solvers import SOLVERS, LinearOperator, Problem, Solver, make_solver, resolve_l1

#: the options :func:`build` reads; :func:`~flamerecon.fit.reconstruct.fit` refuses others.
BUILD_OPTIONS = ("grid", "projector", "silhouette", "hull", "holdout")


@dataclass
class Setup:
    """Everything the solve needs, built once from the scene and the options."""

    scene: Scene
    train: list[int]
    holdout: list[int]
    grid: VoxelGrid
    masks: torch.Tensor  # (B, H, W) bool, every view
    hull: torch.Tensor  # (nz, ny, nx) bool
    voxel_index: torch.Tensor  # (M,) flat indices of hull voxels
    operator: LinearOperator  # (N, M)
    pixels: torch.Tensor  # (N, C) training pixel values inside the silhouettes
    step: float
    row_view: torch.Tensor | None = None  # (N,) long: position in ``train`` of each pixel row
    seconds: float = 0.0  # wall time it took to build (hull, rays, operator)
    assembly_seconds: float = 0.0  # of which the operator (backend choice and assembly)
    options: ReconstructionOptions | None = None  # what it was built with (fit holds to them)
    row_pixel: torch.Tensor | None = None  # (N,) long: each row's pixel b * H * W + v * W + u in the training views

    def training_pixels(self, volume: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The training views' pixels the operator renders for a density (C, nz, ny, nx) on
        the grid: their flat index into (T, H, W) (N,) and A x (N, C), so that a render
        marches only the others (:func:`~flamerecon.operators.projector.render_image`'s
        ``known``); None for a density with nonzeros off the hull (the operator does not see them)."""
        if self.row_pixel is None:
            return None
        with torch.no_grad():
            values = volume.detach().reshape(volume.shape[0], -1)
            off = torch.ones(values.shape[1], dtype=torch.bool, device=values.device)
            off[self.voxel_index.to(values.device)] = False
            if bool(values[:, off].any()):
                return None
            x = values[:, self.voxel_index.to(values.device)].T.to(self.pixels)
            return self.row_pixel, self.operator.forward(x).cpu()

    def __post_init__(self) -> None:
        fields(self)
        B, (H, W) = self.scene.num_views, self.scene.image_size
        views = list_of(integer(0, B - 1), what=f"a list of view indices in [0, {B - 1}]")
        for name in ("train", "holdout"):
            value(f"Setup.{name}", getattr(self, name), views)
        tensor("Setup.masks", self.masks, "(B, H, W) silhouettes of every view", shape=(B, H, W), kind="bool")
        tensor("Setup.hull", self.hull, "(nz, ny, nx) of the grid", shape=self.grid.shape, kind="bool")
        index = tensor("Setup.voxel_index", self.voxel_index, "(M,) flat hull indices", ndim=1, kind="integer")
        pixels = tensor("Setup.pixels", self.pixels, "(N, C) training pixels", ndim=2)
        N, M = int(pixels.shape[0]), int(index.numel())
        if tuple(int(n) for n in self.operator.shape) != (N, M):
            raise wrong_value("Setup.operator", self.operator.shape, f"of shape (N, M) = ({N}, {M}): pixels x hull voxels")
        tensor("Setup.row_view", self.row_view, "(N,) training view of each pixel row", shape=(N,),
               kind="integer", null=True)
        tensor("Setup.row_pixel", self.row_pixel, "(N,) training pixel of each row", shape=(N,),
               kind="integer", null=True)
        value("Setup.step", self.step, number(0, lo_open=True))

    def volume(self, x: torch.Tensor) -> torch.Tensor:
        """Hull values (M, C) -> dense density (C, nz, ny, nx)."""
        return self.grid.dense(x, self.voxel_index)


def scene_grid(options: GridOptions, scene: Scene) -> VoxelGrid:
    """The reconstruction grid: ``options.bbox`` if set, else the scene's box."""
    lo, hi = (options.bbox[0], options.bbox[1]) if options.bbox is not None else (scene.bbox_min, scene.bbox_max)
    res = options.resolution
    return VoxelGrid.from_box(lo, hi, int(res) if isinstance(res, (int, float)) else list(res))


def split_views(scene: Scene, options: ReconstructionOptions) -> tuple[list[int], list[int]]:
    """(training, held-out) view indices of ``scene`` under ``options.holdout`` (see
    :meth:`~flamerecon.scenes.Scene.split`; none held out: every camera fitted)."""
    return scene.split(None if options.holdout is None else list(options.holdout))


def scene_masks(scene: Scene, images: torch.Tensor, options: ReconstructionOptions) -> torch.Tensor:
    """(B, H, W) bool silhouettes: the scene's own masks, else computed from ``images``."""
    if scene.masks is not None:
        return scene.masks.to(images.device)
    return silhouettes(images, **options.silhouette.as_dict())


def build(scene: Scene, options: ReconstructionOptions, device: torch.device | str | None = None,
          grid: VoxelGrid | None = None) -> Setup:
    """Split, silhouettes, visual hull, rays and the operator restricted to them, on ``grid``
    (default: the options', :func:`scene_grid`), on ``device`` (default: ``options.device``). Sets
    torch's thread count as ``options.threads`` says."""
    check_inputs("build", scene, options, device)
    instance("build.grid", grid, VoxelGrid, null=True)
    set_threads(options.threads)
    device = resolve_device(options.device if device is None else str(device))
    started = time.perf_counter()
    train, holdout = split_views(scene, options)
    grid = grid if grid is not None else scene_grid(options.grid, scene)
    check_scene(scene, grid)
    budget = memory_budget(device, options.projector.max_memory_gb)
    check_grid_memory(grid, scene.num_views, device, budget)
    images = scene.images.to(device)
    masks = scene_masks(scene, images, options)
    threshold = float(options.silhouette.threshold or 0.0)
    check_silhouettes(scene, masks, train, options.silhouette)
    cams = cameras_to(camera_subset(scene.cameras, train), device)
    margin = int(options.hull.margin_voxels)
    hull = visual_hull(grid, cams, masks[train], margin)
    if not bool(hull.any()):
        raise explain_empty_hull(scene, grid, cams, masks[train], train, threshold, margin)
    voxel_index = hull.reshape(-1).nonzero().squeeze(1)
    rows = fit_pixels(options.projector.rays, grid, cams, hull, masks[train])
    rays, flat = camera_rays(cams, rows)
    C = images.shape[1]
    pixels = images[train].permute(0, 2, 3, 1).reshape(-1, C)[flat].contiguous()
    row_view = flat // (images.shape[-2] * images.shape[-1])
    step = float(options.projector.step)
    assembly = time.perf_counter()
    backend = choose_backend(options.projector.backend, grid, rays, voxel_index, step, device, budget,
                             options.solver.params.get("max_iters"))
    operator = None
    if backend == "assembled":  # the capture's region operator, where it serves
        operator = capture_operator(cams, grid, masks[train], rows, hull, step, options)
    if operator is None:
        operator = make_operator(backend, grid, rays, voxel_index, step)
    now = time.perf_counter()
    return Setup(scene, train, holdout, grid, masks, hull, voxel_index, operator, pixels, step, row_view,
                 now - started, now - assembly, options, flat.cpu())


def check_inputs(where: str, scene: Scene, options: ReconstructionOptions | None, device) -> None:
    """Refuse a ``scene``, ``options`` (None: the defaults) or ``device`` of the wrong type or
    value given to the function ``where``, naming it (``build.scene: got None; ...``)."""
    instance(f"{where}.scene", scene, Scene)
    instance(f"{where}.options", options, ReconstructionOptions,
             "a ReconstructionOptions (a dict of options goes through ReconstructionOptions.from_dict)",
             null=where != "build")
    instance(f"{where}.device", device, (str, torch.device), "a device name (auto, cpu, cuda, cuda:N)",
             null=True)
    if options is not None:
        options.check()


def check_frame_inputs(where: str, scenes, options: ReconstructionOptions | None, device, what: str) -> None:
    """Refuse ``scenes`` that are not a non-empty list of Scenes (``what``: which frames, for
    the message), then each frame, ``options`` and ``device`` as :func:`check_inputs`."""
    if isinstance(scenes, Scene) or not isinstance(scenes, Sequence):
        raise wrong_type(f"{where}.scenes", scenes, f"a list of Scenes, {what}")
    if len(scenes) < 1:
        raise wrong_value(f"{where}.scenes", scenes, "a list of at least one Scene")
    for i, scene in enumerate(scenes):
        check_inputs(f"{where}.scenes[{i}]", scene, options, device)


def fit_pixels(which: str, grid: VoxelGrid, cams, hull: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """The training pixels (T, H, W) bool whose rays enter the operator: ``silhouette``, the
    silhouette pixels only; ``hull``, also every background pixel whose ray can meet the hull
    (its zero is a constraint: no hull voxel is left unconstrained)."""
    if which == "silhouette":
        return masks
    if which == "hull":
        return masks | hull_footprint(grid, cams, hull)
    raise ConfigError(f"projector.rays: unknown value '{which}'; choose silhouette or hull")


def check_solver_name(name: str) -> None:
    if name not in SOLVERS:
        raise ConfigError(f"solver.name: unknown solver '{name}'; choose one of {sorted(SOLVERS)}")


def make_problem(options: SolverOptions, setup: Setup) -> tuple[Problem, Solver, float]:
    """The solve ``options`` describe on ``setup``: (problem, solver, absolute l1 weight)."""
    instance("make_problem.options", options, SolverOptions)
    instance("make_problem.setup", setup, Setup)
    check_solver_name(options.name)
    l1_rel = None if options.l1 is not None else options.l1_rel  # an absolute weight wins
    try:
        l1 = resolve_l1(setup.operator, setup.pixels, options.l1, l1_rel)
        solver = make_solver(options.name, **options.params)
    except FlameReconError:
        raise
    except ValueError as err:
        raise ConfigError(str(err)) from err
    problem = Problem(setup.operator, setup.pixels, l1, grid_shape=setup.grid.shape,
                      voxel_index=setup.voxel_index)
    return problem, solver, l1


def init_volume(path: str | Path, grid: VoxelGrid, channels: int | None = None) -> torch.Tensor:
    """The density (C, nz', ny', nx') of a finished run (``init=``), which must cover the box of
    ``grid`` (its resolution may differ), have ``channels`` channels (when given) and values a
    solve can start from (:func:`~flamerecon.fit.checks.density_fault`)."""
    try:
        saved = load_density(path)
    except FileNotFoundError as err:
        raise ConfigError(f"init: {err}; give a finished run's folder or its density.npz") from None
    fault = density_fault(saved.density, float(np.linalg.norm(saved.bbox_max - saved.bbox_min)))
    if fault is not None:
        raise ConfigError(f"init: {density_path(path)}: its density {fault}")
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
    cell averages on ``grid`` (:func:`~flamerecon.evaluate.metrics.resample_to`) read at ``voxel_index``.
    A warm start: cells the density is zero on (e.g. outside a coarser level's hull) start at 0."""
    vol = resample_to(volume, grid.shape).to(voxel_index.device)
    return vol.reshape(vol.shape[0], -1)[:, voxel_index].T.contiguous()
