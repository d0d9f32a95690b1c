"""What a reconstruction will hold, told and checked before any work: its rays, voxels, ray
samples per pass, and an upper bound of the process's peak memory, phase by phase: the process
as it stands (its baseline: libraries, the loaded images), every level's grid arrays and
assembled operator (the ladder's rungs, ``grid.levels``, the run's own), the camera fit, and
the scores' renders at the working and at the capture's native resolution. The peak is the
baseline plus the largest phase; it is checked against what the process may use (free memory,
a container's cgroup limit, ``ulimit -v``: :func:`~flamerecon.machine.available_bytes`, or
``projector.max_memory_gb``) and a run that would not fit is refused naming the option that
sizes the phase that does not fit (``grid.resolution``, ``ladder.rungs``, ``scene.downscale``,
``projector.max_memory_gb``).

An operator's nonzeros are bounded from its rows (the training silhouettes' pixels) and their
chords through the box: :data:`ENTRIES_PER_VOXEL` entries per voxel of chord at most. No time is
told for an assembled run: from box-crossing rays, a per-sample cost overestimated a ScalarFlow
frame at 1/2 resolution 130-fold; a matrix-free fallback says its time
(:func:`~flamerecon.operators.projector.matrix_free_seconds`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from flamerecon.errors import MemoryBudgetError
from flamerecon.fit.build import scene_masks, split_views
from flamerecon.fit.checks import DENSE_BYTES_PER_VOXEL, check_grid_memory, memory_budget
from flamerecon.fit.levels import Level
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.geometry.cameras import camera_subset, pixel_rays
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.machine import format_bytes, resident_bytes
from flamerecon.operators import compiled
from flamerecon.operators.projector import (
    ASSEMBLY_CHUNK_SAMPLES,
    CHUNK_SAMPLES,
    Rays,
    camera_rays,
    march_box,
    ray_box,
)
from flamerecon.scenes import Scene

log = logging.getLogger(__name__)

#: pixels per image side of the lattice whose rays measure how much of a view crosses the box
LATTICE = 64
#: bytes per ray a run holds at once: the ray (24), its box entry and exit (8), indices (16),
#: and per channel its pixel, residuals and renders (24)
BYTES_PER_RAY = 48
BYTES_PER_RAY_CHANNEL = 24
#: ray samples per pass above which a run is told it will be long, with the setting that shortens
#: it: a full ScalarFlow frame on 256 cells has 2.6e9 (logged), its 1/4 frame on 64 cells 4.2e7
LONG_RUN_SAMPLES = 1e9
#: an operator row's entries per voxel of its ray's chord through the box, at most: measured
#: 0.79-1.44 (ScalarFlow frames 20-70 at 1/4 and 1/2, grids 64-192: the hull fills less of a
#: finer grid's box); a line meets at most 4 (|dx| + |dy| + |dz|) <= 6.9 new trilinear corners
#: per voxel of length, whatever the hull
ENTRIES_PER_VOXEL = 2.0
#: bytes of one assembled entry stored once (float32 value, int32 column)
ENTRY_BYTES = 8
#: an assembly's temporaries per segment of a block: the compiled march's scratch (8 entries
#: of 8 bytes a segment) and its rows' copies; the torch path's (160 bytes a sample of a chunk,
#: and a transpose block's 48 bytes an entry, about one a sample)
ASSEMBLY_BYTES_PER_SEGMENT = 2 * 8 * 8
ASSEMBLY_BYTES_PER_SAMPLE = 160 + 48
#: bytes per pixel and channel while a view is scored: its render (the march's buffer, the
#: image, its copy), SSIM's maps (float32) and the detail band's (float64)
SCORE_BYTES_PER_PIXEL = 3 * 4 + 15 * 4 + 4 * 8
#: bytes per sample and channel of an autograd march (the camera fit's renders), per chunk
AUTOGRAD_BYTES_PER_SAMPLE = 100
#: what the allocator keeps beyond the phases' own arrays (freed blocks not returned, the
#: solver's vectors): measured within this of the bound on the configurations of docs/results.md
SLACK_BYTES = 256 * 2**20


@dataclass(frozen=True)
class Phase:
    """A step of the run and the bytes it holds beyond the baseline, with the option that
    sizes it (named when it does not fit)."""

    name: str
    bytes: int
    field: str


@dataclass(frozen=True)
class Workload:
    rays: int  # pixels of every view whose ray crosses the box
    voxels: int
    samples: int  # ray samples of one pass over them
    baseline: int  # resident bytes of the process now
    phases: tuple[Phase, ...]

    @property
    def largest(self) -> Phase:
        return max(self.phases, key=lambda p: p.bytes)

    @property
    def added(self) -> int:
        """Bytes the run will add to what it holds now: the largest phase and the allocator's slack."""
        return self.largest.bytes + SLACK_BYTES

    @property
    def bytes(self) -> int:
        """The bound of the process's peak: the baseline and what the run adds."""
        return self.baseline + self.added

    def __str__(self) -> str:
        return (f"{self.rays:.3g} rays, {self.voxels:.3g} voxels, {self.samples:.3g} ray samples per pass: "
                f"a peak of at most {format_bytes(self.bytes)} ({format_bytes(self.baseline)} held now, "
                f"{format_bytes(self.added)} more while {self.largest.name})")


def box_rays(scene: Scene, grid: VoxelGrid, step: float) -> tuple[int, int]:
    """(rays of every view that cross the box, ray samples of one pass over them): each view's
    share of rays crossing the box and their mean chord, measured on a lattice of
    :data:`LATTICE`\\ ² pixels, scaled to its pixels."""
    H, W = scene.image_size
    n = LATTICE
    uv = torch.stack(torch.meshgrid(torch.linspace(0.5, W - 0.5, n), torch.linspace(0.5, H - 0.5, n),
                                    indexing="xy"), -1).reshape(1, -1, 2)
    cams = scene.cameras
    origins, dirs = pixel_rays(cams, uv.expand(cams.batch_size, -1, -1).to(cams.intrinsics.device).contiguous())
    near, far = ray_box(Rays(origins.reshape(-1, 3), dirs.reshape(-1, 3)), *march_box(grid, origins.device))
    chord = (far - near).clamp_min(0).reshape(cams.batch_size, -1)  # world units (unit directions)
    pixels = scene.num_views * H * W
    ds = float(step) * float(grid.voxel_size().min())
    return int(float((chord > 0).float().mean()) * pixels), int(float(chord.mean()) / ds * pixels)


def silhouette_chords(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid) -> tuple[int, float]:
    """(the operator's rows, their chords through the box in voxels of ``grid`` in all), at
    the scene's images: the training silhouettes' pixels (``projector.rays=hull`` adds the
    background pixels whose ray meets the hull: every box-crossing ray is counted then)."""
    train, _ = split_views(scene, options)
    cams = camera_subset(scene.cameras, train)
    if options.projector.rays == "hull":
        keep = None
    else:
        keep = scene_masks(scene, scene.images, options)[train]
    rays, _ = camera_rays(cams, keep)
    near, far = ray_box(rays, *march_box(grid, rays.origins.device))
    chord = (far - near).clamp_min(0)
    if keep is None:
        rows = int((chord > 0).sum())
    else:
        rows = len(rays)
    return rows, float(chord.sum()) / float(grid.voxel_size().min())


def level_bytes(rows: int, chord_voxels: float, grid: VoxelGrid, scene: Scene, channels: int, step: float,
                device) -> int:
    """An assembled level's bytes: its grid's dense arrays, its rays and pixels, its operator
    (A, and A^T where the adjoint needs it) bounded by :data:`ENTRIES_PER_VOXEL`, and the
    assembly's temporaries (for its segments, at most a block's)."""
    copies = 1 if compiled.available(device) else 2
    nnz = ENTRIES_PER_VOXEL * chord_voxels
    segments = min(chord_voxels / float(step), compiled.BLOCK_SEGMENTS if copies == 1 else ASSEMBLY_CHUNK_SAMPLES)
    temporaries = segments * (ASSEMBLY_BYTES_PER_SEGMENT if copies == 1 else ASSEMBLY_BYTES_PER_SAMPLE)
    return int(grid.num_voxels * (DENSE_BYTES_PER_VOXEL + scene.num_views)
               + rows * (BYTES_PER_RAY + BYTES_PER_RAY_CHANNEL * channels + 8)
               + copies * ENTRY_BYTES * nnz + temporaries)


def scoring_bytes(scene: Scene, native: tuple[int, int] | None) -> int:
    """The scores' renders: every view at the working resolution, then one view at a time scored
    (:data:`SCORE_BYTES_PER_PIXEL`); with ``native`` (H, W) the capture's own frame loaded and its
    held-out views rendered and scored there too."""
    (H, W), C, V = scene.image_size, int(scene.images.shape[1]), scene.num_views
    working = V * C * H * W * 4 + C * H * W * SCORE_BYTES_PER_PIXEL
    if native is None:
        return working
    Hn, Wn = native
    return working + V * C * Hn * Wn * 4 * 2 + C * Hn * Wn * SCORE_BYTES_PER_PIXEL


def workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, levels: list[Level] | None = None,
             native: tuple[int, int] | None = None, device: torch.device | str = "cpu") -> Workload:
    """The estimate for ``scene`` on ``grid`` after ``levels`` (the ladder's rungs, ``grid.levels``:
    :func:`~flamerecon.fit.reconstruct.levels_of`), scored also at the ``native`` (H, W) image size
    when the run works below it."""
    C = int(scene.images.shape[1])
    rows, chord = silhouette_chords(scene, options, grid)
    step = float(options.projector.step)
    phases = [Phase("the final grid is solved", level_bytes(rows, chord, grid, scene, C, step, device),
                    "grid.resolution")]
    for level in levels or []:
        scale = float(grid.voxel_size().min()) / float(level.grid.voxel_size().min())  # chords in its voxels
        area = 1.0 if level.downscale is None else (scene_downscale(scene) / level.downscale) ** 2
        field = "ladder.rungs" if level.downscale is not None else "grid.levels"
        phases.append(Phase(f"the level {'x'.join(map(str, level.grid.resolution))} is solved",
                            level_bytes(int(rows * area), chord * area * scale, level.grid, scene, C, step, device),
                            field))
    scoring = scoring_bytes(scene, native)  # the final operator is held while the result is scored
    phases.append(Phase("the result is scored", phases[0].bytes + scoring,
                        "scene.downscale" if scoring > phases[0].bytes else "grid.resolution"))
    if options.calibration.refine != "none" and not options.calibration.file:
        cal_grid = grid if not options.calibration.resolution else VoxelGrid.from_box(
            grid.bbox_min, grid.bbox_max, options.calibration.resolution)
        scale = float(grid.voxel_size().min()) / float(cal_grid.voxel_size().min())
        phases.append(Phase("the cameras are fitted", level_bytes(rows, chord * scale, cal_grid, scene, C, step, device)
                            + CHUNK_SAMPLES * C * AUTOGRAD_BYTES_PER_SAMPLE, "calibration.resolution"))
    rays, samples = box_rays(scene, grid, step)
    return Workload(rays, grid.num_voxels, samples, resident_bytes(), tuple(phases))


def scene_downscale(scene: Scene) -> int:
    """The downscale the scene was loaded at (1 when not told)."""
    return int((scene.meta.get("config") or {}).get("downscale") or 1)


def check_workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, device: torch.device,
                   levels: list[Level] | None = None, native: tuple[int, int] | None = None) -> Workload:
    """Log :func:`workload` (INFO), and refuse one whose peak exceeds what the process may use
    (``projector.max_memory_gb``, else most of what ``device`` has free), naming the option that
    sizes the phase that does not fit and the settings that shrink it."""
    budget = memory_budget(device, options.projector.max_memory_gb)
    check_grid_memory(grid, scene.num_views, device, budget)  # the grid alone: its own message
    for level in levels or []:
        check_grid_memory(level.grid, scene.num_views, device, budget,
                          "ladder.rungs" if level.downscale is not None else "grid.levels")
    if options.calibration.refine != "none" and options.calibration.resolution:
        check_grid_memory(VoxelGrid.from_box(grid.bbox_min, grid.bbox_max, options.calibration.resolution),
                          scene.num_views, device, budget, "calibration.resolution")
    found = workload(scene, options, grid, levels, native, device)
    if budget is not None and found.added > budget:
        raise MemoryBudgetError(refusal(scene, options, grid, found, budget, device))
    log.info("estimate: %s on %s", found, device)
    if found.samples > LONG_RUN_SAMPLES:
        H, W = scene.image_size
        rungs = "" if options.ladder.rungs else ("; a ladder (ladder.rungs=[[4,128],[2,192]]) solves coarser levels "
                                                 "first and fits the cameras at 1/4")
        log.warning("a large frame: %d views of %dx%d px, %.3g ray samples per pass: the camera fit and each solve "
                    "take minutes here; scene.downscale=%d works on 1/%d of the pixels%s", scene.num_views, W, H,
                    found.samples, 4 if min(H, W) >= 1000 else 2, 16 if min(H, W) >= 1000 else 4, rungs)
    return found


def refusal(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, found: Workload, budget: int,
            device) -> str:
    """The one-line refusal of a run whose peak ``found`` exceeds ``budget``: the field at fault
    first (``projector.max_memory_gb`` when it, not the machine, sets the budget too low)."""
    phase = found.largest
    H, W = scene.image_size
    nx, ny, nz = grid.resolution
    need = (f"{scene.num_views} views of {W}x{H} px on a {nx}x{ny}x{nz} grid need about {format_bytes(found.added)} "
            f"more memory while {phase.name} (a peak of at most {format_bytes(found.bytes)})")
    free = memory_budget(device, None)
    if options.projector.max_memory_gb is not None and (free is None or found.added <= free):
        return (f"projector.max_memory_gb: {need}, but it allows {format_bytes(budget)}; raise it (this machine has "
                f"{'an unknown amount' if free is None else format_bytes(free)} free) or shrink the run")
    fixes = {"ladder.rungs": "coarser or fewer rungs (ladder.rungs)",
             "calibration.resolution": "a coarser camera-fit grid (calibration.resolution)",
             "grid.levels": "coarser grid.levels"}
    first = fixes.get(phase.field, "a larger scene.downscale (or scene.width/height), a smaller grid.resolution")
    return (f"{phase.field}: {need}, but {format_bytes(budget)} is available on {device}; try {first}, or allow "
            "more with projector.max_memory_gb")
