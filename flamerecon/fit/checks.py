"""Refuse unusable input before the work starts, with a message that says how to fix it.

Each check raises a :class:`~flamerecon.errors.FlameReconError` whose one-line message names
the scene's file (``Scene.source``) or the config field at fault and what to try.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.errors import ConfigError, HullError, MemoryBudgetError
from flamerecon.fit.options import SilhouetteOptions
from flamerecon.geometry.cameras import K_of, camera_subset, pixel_rays
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import carve_counts, visual_hull
from flamerecon.geometry.photometry import linearize
from flamerecon.geometry.silhouettes import silhouette_signal, silhouettes
from flamerecon.machine import available_bytes, format_bytes
from flamerecon.operators.projector import (
    Rays,
    assembled_bound,
    assembled_memory,
    march_box,
    matrix_free_seconds,
    ray_box,
)
from flamerecon.outputs.cameras_file import cameras_from_records, read_camera_file
from flamerecon.progress import duration
from flamerecon.scenes import Scene, SceneError

if TYPE_CHECKING:
    from flamerecon.fit.options import ReconstructionOptions

log = logging.getLogger(__name__)

#: an assembled operator at least this large is announced (INFO) before it is built: it takes
#: tens of seconds (a full-resolution ScalarFlow frame on a 256-cell grid: 2.2 GiB, about 25 s)
LOUD_OPERATOR_BYTES = 2**30
#: share of the free memory a run may plan to use when ``projector.max_memory_gb`` is unset.
MEMORY_HEADROOM = 0.8
#: bytes per voxel of the dense arrays a run holds at once: voxel centres (12), carving (1 per
#: camera), the hull and its dilation (8), and a few (C=3)-channel float volumes (48).
DENSE_BYTES_PER_VOXEL = 68
#: pixels per image side tested for whether a camera sees the box.
VISIBILITY_LATTICE = 64
#: the brightest line integral a warm-start density may reach, in image units (images are in
#: [0, 1]): its peak times the box diagonal beyond this is no density of a capture (1e30, units mixed up)
ABSURD_INTEGRAL = 1e3


def _where(scene: Scene) -> str:
    return scene.source or f"scene '{scene.name}'"


def check_scene(scene: Scene, grid: VoxelGrid) -> None:
    """Shapes agree, images are finite, K and the rotations are sane, every camera sees the box.

    Loaders name their own file's fields; this catches what any loader could let through.
    """
    where = _where(scene)
    cams = scene.cameras
    B = scene.images.shape[0]
    if scene.images.ndim != 4:
        raise SceneError(f"{where}: images must be (views, channels, H, W), got {tuple(scene.images.shape)}")
    if not (B == len(scene.views) == cams.batch_size):
        raise SceneError(
            f"{where}: {B} images, {len(scene.views)} view names and {cams.batch_size} cameras; "
            "each view needs one of each"
        )
    H, W = scene.image_size
    for i, name in enumerate(scene.views):
        ch, cw = int(cams.height[i]), int(cams.width[i])
        if (ch, cw) != (H, W):
            raise SceneError(
                f"{where}: view '{name}': the image is {W}x{H} but its calibration says {cw}x{ch} "
                "(width, height); rescale K with the image or fix the calibration"
            )
    bad = (~torch.isfinite(scene.images)).flatten(1).sum(1)
    for i in bad.nonzero().flatten().tolist():
        raise SceneError(
            f"{where}: view '{scene.views[i]}': the image holds {int(bad[i])} NaN/Inf values; "
            "repair or drop the frame, or hold the view out"
        )
    K = K_of(cams)
    R = cams.extrinsics[:, :3, :3].double()
    eye = torch.eye(3, dtype=R.dtype)
    for i, name in enumerate(scene.views):
        if not (torch.isfinite(K[i]).all() and torch.isfinite(cams.extrinsics[i]).all()):
            raise SceneError(f"{where}: view '{name}': K or world_to_camera holds NaN/Inf")
        if K[i, 0, 0] <= 0 or K[i, 1, 1] <= 0:
            raise SceneError(
                f"{where}: view '{name}': K focal lengths must be positive, got "
                f"fx={float(K[i, 0, 0]):g}, fy={float(K[i, 1, 1]):g}"
            )
        err = float((R[i] @ R[i].T - eye).abs().max())
        if err > 1e-3 or float(torch.linalg.det(R[i])) < 0:
            raise SceneError(
                f"{where}: view '{name}': the rotation of world_to_camera is not orthonormal with "
                f"det +1 (|R R^T - I| = {err:.2g}, det = {float(torch.linalg.det(R[i])):.3g})"
            )
    seen = sees_box(cams, grid)
    for i in (~seen).nonzero().flatten().tolist():
        lo, hi = [round(v, 4) for v in grid.bbox_min], [round(v, 4) for v in grid.bbox_max]
        cx, cy = float(K[i, 0, 2]), float(K[i, 1, 2])
        fix = ("check its world_to_camera (pose, axis convention) or set grid.bbox" if 0 <= cx <= W and 0 <= cy <= H
               else f"its principal point ({cx:.1f}, {cy:.1f}) px lies outside the {W}x{H} image: check K's cx, cy "
               "first (pixels of this image), then its pose")
        raise SceneError(f"{where}: view '{scene.views[i]}': the camera does not see the box {lo}..{hi}; {fix}")


def check_before_work(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid,
                      read_at: int | None = None, first: VoxelGrid | None = None) -> None:
    """What a reconstruction of ``scene`` with ``options`` on ``grid`` refuses before any work
    (each refusal one line): the split (``holdout``), a confidence asked for with fewer than two
    training cameras, a ``calibration.file`` that cannot give the training cameras (at the
    images it is read with: the scene's, or with ``read_at`` the ladder's coarsest rung's, that
    downscale of the capture), the cameras against the box (:func:`check_scene`), the
    training views' silhouettes (:func:`check_silhouettes`), an empty visual hull on the first
    grid solved (``first``, default ``grid``) and, for ``solver=lars``, more hull voxels on
    ``grid`` than ``solver.max_voxels``; the build checks them again on each level."""
    train, _ = scene.split(None if options.holdout is None else list(options.holdout))
    if options.uncertainty.enabled and len(train) < 2:
        raise ConfigError(
            f"uncertainty.enabled: the confidence needs at least two training cameras (its ensemble leaves each "
            f"out in turn; with one it sees nothing the cameras leave open and predicts far too high a PSNR), "
            f"this run trains on {len(train)}; hold out fewer cameras (holdout=...), or leave uncertainty off")
    if options.calibration.file is not None:  # read (and refused) before any work, as the run reads it later
        path = options.calibration.file
        height, width = scene.cameras.height, scene.cameras.width
        if read_at is not None:  # the capture's pixels (scene.downscale's factor back) over the rung's
            own = int((scene.meta.get("config") or {}).get("downscale") or 1)
            height, width = (torch.div(size * own, read_at, rounding_mode="floor") for size in (height, width))
        cameras_from_records(read_camera_file(path)["cameras"], scene.views, height, width,
                             f"calibration.file: {path}")
    check_scene(scene, grid)
    masks = scene.masks
    if masks is None:
        masks = torch.zeros(scene.num_views, *scene.image_size, dtype=torch.bool, device=scene.images.device)
        masks[train] = silhouettes(scene.images[train], **options.silhouette.as_dict())
    check_silhouettes(scene, masks, train, options.silhouette)
    check_hull(scene, options, masks, train, grid, first or grid)


def check_hull(scene: Scene, options: ReconstructionOptions, masks: torch.Tensor, train: list[int],
               grid: VoxelGrid, first: VoxelGrid) -> None:
    """Refuse a ``grid`` or ``first`` too big to carve (:func:`check_grid_memory`), an empty
    visual hull of the ``train`` cameras' silhouettes ``masks`` (B, H, W) on ``first``
    (:func:`explain_empty_hull`), and for ``solver=lars`` a hull on ``grid`` of more
    voxels than ``solver.max_voxels`` (the path's dense Gram matrix)."""
    from flamerecon.solvers.lars import too_many_voxels

    cams = camera_subset(scene.cameras, train)
    device = cams.intrinsics.device
    budget = memory_budget(device, options.projector.max_memory_gb)
    for carved in (grid, first):  # the grid alone must fit before it is carved: its own message
        check_grid_memory(carved, scene.num_views, device, budget)
    masks = masks[train].to(device)
    margin = int(options.hull.margin_voxels)
    hull = visual_hull(first, cams, masks, margin)
    if not bool(hull.any()):
        raise explain_empty_hull(scene, first, cams, masks, train, float(options.silhouette.threshold or 0.0), margin)
    if options.solver.name == "lars":
        voxels = int((hull if first is grid else visual_hull(grid, cams, masks, margin)).sum())
        refusal = too_many_voxels(voxels, int(options.solver.params.get("max_voxels", 5000)))
        if refusal is not None:
            raise ConfigError(refusal)


def density_fault(density: np.ndarray | torch.Tensor, diagonal: float) -> str | None:
    """What makes ``density`` (C, nz, ny, nx) unusable as a warm start on a box of ``diagonal``
    world units (NaN/Inf, negative values, a peak whose line integrals no image in [0, 1] could
    hold, see :data:`ABSURD_INTEGRAL`), or None when it can start a solve."""
    d = torch.as_tensor(density)
    bad = int((~torch.isfinite(d)).sum())
    if bad:
        return f"holds {bad} NaN/Inf values; warm start from a run that finished, not one that diverged"
    negative = int((d < 0).sum())
    if negative:
        return (f"holds {negative} negative values (min {float(d.min()):.3g}) where an emission density is >= 0; "
                "warm start from a nonnegative solver's run (solver=cgls needs solver.nonneg=true)")
    peak = float(d.max()) if d.numel() else 0.0
    if peak * diagonal > ABSURD_INTEGRAL:
        return (f"peaks at {peak:.3g}: a ray through the box would integrate to about {peak * diagonal:.3g}, "
                "against images in [0, 1]; it is no density of this capture")
    return None


def sees_box(cams: PinholeCamera, grid: VoxelGrid) -> torch.Tensor:
    """(B,) bool: whether any ray of a lattice of pixels (edges included) meets the grid's box."""
    B = cams.batch_size
    H, W = int(cams.height[0]), int(cams.width[0])
    n = VISIBILITY_LATTICE
    u = torch.linspace(0.0, float(W), n)
    v = torch.linspace(0.0, float(H), n)
    uv = torch.stack(torch.meshgrid(u, v, indexing="xy"), -1).reshape(1, -1, 2).expand(B, -1, -1)
    origins, dirs = pixel_rays(cams, uv.to(cams.intrinsics.device).contiguous())
    lo, hi = march_box(grid, origins.device)
    t_near, t_far = ray_box(Rays(origins.reshape(-1, 3), dirs.reshape(-1, 3)), lo, hi)
    return (t_far > t_near).reshape(B, -1).any(1).cpu()


def memory_budget(device: torch.device, max_memory_gb: float | None) -> int | None:
    """Bytes a run may plan to use: ``projector.max_memory_gb`` when set, else
    :data:`MEMORY_HEADROOM` of what ``device`` has free (None where that is unknown)."""
    if max_memory_gb is not None:
        return int(float(max_memory_gb) * 2**30)
    free = available_bytes(device)
    return None if free is None else int(MEMORY_HEADROOM * free)


def check_grid_memory(grid: VoxelGrid, n_views: int, device: torch.device, budget: int | None,
                      field: str = "grid.resolution") -> None:
    """Refuse a grid whose dense arrays alone would not fit in ``budget`` bytes (the option
    that sized it: ``field``)."""
    need = grid.num_voxels * (DENSE_BYTES_PER_VOXEL + n_views)
    if budget is not None and need > budget:
        nx, ny, nz = grid.resolution
        raise MemoryBudgetError(
            f"{field}: a {nx}x{ny}x{nz} grid ({grid.num_voxels:.3g} voxels) needs about "
            f"{format_bytes(need)} for its dense arrays but {format_bytes(budget)} is available on "
            f"{device}; use a smaller {field}"
        )


def choose_backend(
    requested: str, grid: VoxelGrid, rays: Rays, voxel_index: torch.Tensor, step: float,
    device: torch.device, budget: int | None, iterations: int | None = None,
) -> str:
    """``projector.backend`` to use: ``auto`` is ``assembled`` when its estimated peak memory
    fits in ``budget`` bytes, else ``matrix_free``, told with its expected time for
    ``iterations`` (:func:`~flamerecon.operators.projector.matrix_free_seconds`) and the ways out; an
    explicit ``assembled`` that would not fit is refused with the figures and the alternatives."""
    if requested == "matrix_free":
        return requested
    if requested not in ("auto", "assembled"):
        raise ConfigError(
            f"projector.backend: unknown backend '{requested}'; use auto, assembled or matrix_free"
        )
    most = assembled_bound(grid, rays, voxel_index, step)
    if most < LOUD_OPERATOR_BYTES and (budget is None or most <= budget):
        return "assembled"  # surely small enough: no sampled estimate needed
    est = assembled_memory(grid, rays, voxel_index, step)
    if budget is None or est.peak_bytes <= budget:
        if est.peak_bytes >= LOUD_OPERATOR_BYTES:
            log.info("operator: %d rays x %d hull voxels, about %.3g nonzeros: %s for %s (%s while it "
                     "is assembled)", len(rays), int(voxel_index.numel()), est.nnz, format_bytes(est.operator_bytes),
                     est.stored, format_bytes(est.peak_bytes))
        return "assembled"
    figure = (
        f"the assembled operator for {len(rays)} rays x {int(voxel_index.numel())} hull voxels "
        f"needs about {format_bytes(est.operator_bytes)} (~{est.nnz:.3g} nonzeros, {est.stored}) and "
        f"about {format_bytes(est.peak_bytes)} while it is built, but {format_bytes(budget)} is "
        f"available on {device}"
    )
    if requested == "auto":
        seconds = matrix_free_seconds(rays, grid, step, voxel_index, iterations or 100, torch.get_num_threads())
        log.warning("projector.backend=auto: %s; using the matrix-free backend, whose products march every ray "
                    "again: about %s for %d iterations here. To keep the assembled one: free memory or raise "
                    "projector.max_memory_gb, or shrink the operator (scene.downscale, grid.resolution); or keep the "
                    "iterations few (a ladder, ladder.rungs, solves coarser levels first)", figure,
                    duration(seconds), iterations or 100)
        return "matrix_free"
    nx, ny, nz = grid.resolution
    raise MemoryBudgetError(
        f"projector.backend=assembled: {figure}; use projector.backend=matrix_free (or auto), a "
        f"smaller grid.resolution (now {nx}x{ny}x{nz}) or coarser images (scene.downscale=2)"
    )


def check_silhouettes(scene: Scene, masks: torch.Tensor, train: list[int], options: SilhouetteOptions) -> None:
    """Refuse training views whose silhouette ``masks`` (B, H, W) is empty: each would carve
    away the whole box. Names the setting that emptied the first one (:func:`why_empty`)."""
    empty = [v for v in train if not bool(masks[v].any())]
    if not empty:
        return
    names = [scene.views[v] for v in empty]
    every = len(empty) == len(train)
    what = ("every training view's silhouette is empty" if every
            else f"the silhouette of view(s) {names} is empty, so they would carve away the whole box")
    cause, fix = why_empty(scene, empty[0], options)
    raise HullError(f"{_where(scene)}: {what}: {cause}; {fix}"
                    + ("" if every else f" or hold those views out (holdout=[...{names[0]}])"))


def why_empty(scene: Scene, v: int, options: SilhouetteOptions) -> tuple[str, str]:
    """(cause, what to try) for view ``v``'s empty silhouette: the setting without which it
    would not be empty (speck removal, the black level, the threshold), found by computing the
    silhouette again with it changed; each suggested value is one that gives a silhouette."""
    name, kept = scene.views[v], options.as_dict()

    def nonempty(image: torch.Tensor, **changed) -> bool:
        return bool(silhouettes(image, **{**kept, **changed}).any())

    image, speck = scene.images[v:v + 1].cpu(), int(options.speck_px)
    if scene.masks is not None:
        return f"the scene's own mask of view '{name}' is empty", "check its mask file"
    if speck > 0 and nonempty(image, speck_px=0):
        works = next(k for k in range(speck - 1, -1, -1) if nonempty(image, speck_px=k))
        cause = (f"silhouette.speck_px={speck} drops every blob of view '{name}' above the threshold as a "
                 f"speck (blobs smaller than {2 * speck + 1}x{2 * speck + 1} pixels)")
        return cause, f"try silhouette.speck_px={works}"
    black = float((scene.response or {}).get("black_level") or 0.0)
    if black > 0 and scene.recorded_images is not None:
        recorded = scene.recorded_images[v:v + 1].cpu()
        for lower in (0.5 * black, 0.25 * black, 0.0):
            if nonempty(linearize(recorded, scene.response["gamma"], lower)):
                cause = (f"scene.black_level={black:g} leaves no pixel of view '{name}' above the threshold "
                         f"(brightest recorded value {float(recorded.amax()):.3g})")
                return cause, f"try scene.black_level={lower:.3g}"
    peak = float(silhouette_signal(image, blur_px=float(options.blur_px)).max())
    if peak <= 0:
        return f"view '{name}' is black", "check its image file"
    level = f"silhouette.threshold={options.threshold:g}" if options.method == "threshold" else \
        f"the level silhouette.method=otsu chose (silhouette.threshold={options.threshold})"
    return (f"{level} is above every pixel of view '{name}' (brightest pixel {peak:.3g})",
            f"try silhouette.threshold={0.5 * peak:.3g}" + (" and silhouette.method=threshold"
                                                               if options.method != "threshold" else ""))


def explain_empty_hull(
    scene: Scene, grid: VoxelGrid, cams: PinholeCamera, masks: torch.Tensor, train: list[int],
    threshold: float, margin_voxels: int,
) -> HullError:
    """The error for an empty visual hull: which training camera carves away the voxels all the
    others keep, and the silhouette threshold / hull margin to try."""
    carved = carve_counts(grid, cams, masks)  # (B, nz, ny, nx)
    alone = (carved & (carved.sum(0) == 1)[None]).flatten(1).sum(1)  # voxels only b carves
    b = int(alone.argmax())
    name = scene.views[train[b]]
    cover = float(masks[b].float().mean())
    if int(alone[b]) > 0:
        culprit = (
            f"camera '{name}' alone carves away the {int(alone[b])} voxels every other camera "
            f"keeps (its silhouette covers {100 * cover:.1f}% of its image)"
        )
        where = "or check that view's calibration"
    else:
        lo, hi = ([round(float(v), 4) for v in end] for end in (grid.bbox_min, grid.bbox_max))
        culprit = "no single camera is to blame: the silhouettes do not overlap inside the box"
        where = f"or check that the box {lo}..{hi} (grid.bbox) holds the flame"
    return HullError(
        f"{_where(scene)}: the visual hull on the {'x'.join(map(str, grid.resolution))} grid is "
        f"empty; {culprit}; try silhouette.threshold={0.5 * threshold:.3g} (now {threshold:g}) or "
        f"hull.margin_voxels={margin_voxels + 2} (now {margin_voxels}), {where}"
    )


def check_density_fits(path, density, scene: Scene, grid: VoxelGrid, config_file) -> None:
    """Refuse to score a saved density (:class:`~flamerecon.outputs.export.Density`) against a scene it
    was not made for: its channels, fitted views and grid (box and cells) must be those of
    ``scene`` and of ``grid``, the grid the run's config (``config_file``) gives."""
    from flamerecon.outputs.export import DensityFileError

    C = int(density.density.shape[0])
    if C != int(scene.images.shape[1]):
        raise DensityFileError(
            f"{path}: field 'density' has {C} channel(s) but scene '{scene.name}' of {config_file} "
            f"has {int(scene.images.shape[1])}; the density was made for another scene (two runs "
            "into one folder?): evaluate the folder the density was written in"
        )
    unknown = [v for v in density.views if v not in scene.views]
    if unknown:
        raise DensityFileError(
            f"{path}: field 'views': the density was fitted to views {unknown} that scene "
            f"'{scene.name}' of {config_file} does not have ({scene.views}); it was made for another scene"
        )
    shape = tuple(int(n) for n in density.density.shape[1:])
    same_box = np.allclose(density.bbox_min, grid.bbox_min) and np.allclose(density.bbox_max, grid.bbox_max)
    if shape != tuple(grid.shape) or not same_box:
        nz, ny, nx = shape
        lo, hi = ([round(float(v), 4) for v in box] for box in (density.bbox_min, density.bbox_max))
        glo, ghi = ([round(float(v), 4) for v in box] for box in (grid.bbox_min, grid.bbox_max))
        raise DensityFileError(
            f"{path}: field 'density' is a {nx}x{ny}x{nz} grid over the box {lo}..{hi} but "
            f"{config_file} gives {'x'.join(map(str, grid.resolution))} cells over {glo}..{ghi}; "
            "the density and the config come from different runs"
        )
