"""What a reconstruction will hold, told before the work: its rays (every view's pixels whose
ray crosses the box), voxels, ray samples per pass and memory. Huge images on a tiny grid used
to run silently for minutes: :func:`check_workload` logs the estimate (one INFO line) and
refuses what clearly exceeds the memory available. No time is told: from box-crossing rays, a
per-sample cost overestimated a ScalarFlow frame at 1/2 resolution 130-fold (3.8 h against
about 100 s: the operator holds only the silhouettes' rays, inside the hull)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from flamerecon.errors import MemoryBudgetError
from flamerecon.fit.checks import DENSE_BYTES_PER_VOXEL, check_grid_memory, memory_budget
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.geometry.cameras import pixel_rays
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.machine import format_bytes
from flamerecon.operators.projector import (
    Rays,
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
#: ray samples per pass above which a run is told it will be long, with the setting that shortens
#: it: a full ScalarFlow frame on 256 cells has 2.6e9 (logged), its 1/4 frame on 64 cells 4.2e7
LONG_RUN_SAMPLES = 1e9
BYTES_PER_RAY_CHANNEL = 24
@dataclass(frozen=True)
class Workload:
    rays: int  # pixels of every view whose ray crosses the box
    voxels: int
    samples: int  # ray samples of one pass over them
    ray_bytes: int
    voxel_bytes: int

    @property
    def bytes(self) -> int:
        return self.ray_bytes + self.voxel_bytes

    def __str__(self) -> str:
        return (f"{self.rays:.3g} rays, {self.voxels:.3g} voxels, {self.samples:.3g} ray samples per pass: "
                f"about {format_bytes(self.bytes)} of memory")


def workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid) -> Workload:
    """The estimate for ``scene`` on ``grid``: each view's share of rays crossing the box and
    their mean chord, measured on a lattice of :data:`LATTICE`\\ ² pixels, scaled to its
    pixels (an upper bound: the operator keeps only the silhouettes' rays)."""
    H, W = scene.image_size
    C = int(scene.images.shape[1])
    n = LATTICE
    uv = torch.stack(torch.meshgrid(torch.linspace(0.5, W - 0.5, n), torch.linspace(0.5, H - 0.5, n),
                                    indexing="xy"), -1).reshape(1, -1, 2)
    cams = scene.cameras
    origins, dirs = pixel_rays(cams, uv.expand(cams.batch_size, -1, -1).to(cams.intrinsics.device).contiguous())
    near, far = ray_box(Rays(origins.reshape(-1, 3), dirs.reshape(-1, 3)), *march_box(grid, origins.device))
    chord = (far - near).clamp_min(0).reshape(cams.batch_size, -1)  # world units (unit directions)
    hit = float((chord > 0).float().mean())
    ds = float(options.projector.step) * float(grid.voxel_size().min())
    pixels = scene.num_views * H * W
    rays = int(hit * pixels)
    samples = int(float(chord.mean()) / ds * pixels)
    ray_bytes = rays * (BYTES_PER_RAY + BYTES_PER_RAY_CHANNEL * C)
    voxel_bytes = grid.num_voxels * (DENSE_BYTES_PER_VOXEL + scene.num_views)
    return Workload(rays, grid.num_voxels, samples, ray_bytes, voxel_bytes)


def check_workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, device: torch.device) -> Workload:
    """Log :func:`workload` (INFO), and refuse one whose
    memory exceeds the budget (``projector.max_memory_gb``, else most of what ``device`` has
    free) with the settings that shrink it."""
    budget = memory_budget(device, options.projector.max_memory_gb)
    check_grid_memory(grid, scene.num_views, device, budget)  # the grid alone: its own message
    found = workload(scene, options, grid)
    if budget is not None and found.bytes > budget:
        H, W = scene.image_size
        nx, ny, nz = grid.resolution
        images = (f"scene.downscale: {scene.num_views} views of {W}x{H} px give {found.rays:.3g} rays through the "
                  f"box, which need about {format_bytes(found.ray_bytes)}")
        cells = (f"grid.resolution: a {nx}x{ny}x{nz} grid needs about {format_bytes(found.voxel_bytes)} for its "
                 "dense arrays")
        first, then = (images, cells) if found.ray_bytes >= found.voxel_bytes else (cells, images)
        raise MemoryBudgetError(
            f"{first} and {then.split(': ', 1)[1]}, in all {format_bytes(found.bytes)}, but "
            f"{format_bytes(budget)} is available on {device}; work on smaller images (a larger scene.downscale, "
            "or scene.width/height), a smaller grid.resolution, or allow more with projector.max_memory_gb")
    log.info("estimate: %s on %s", found, device)
    if found.samples > LONG_RUN_SAMPLES:
        H, W = scene.image_size
        rungs = "" if options.ladder.rungs else ("; a ladder (ladder.rungs=[[4,128],[2,192]]) solves coarser levels "
                                                 "first and fits the cameras at 1/4")
        log.warning("a large frame: %d views of %dx%d px, %.3g ray samples per pass: the camera fit and each solve "
                    "take minutes here; scene.downscale=%d works on 1/%d of the pixels%s", scene.num_views, W, H,
                    found.samples, 4 if min(H, W) >= 1000 else 2, 16 if min(H, W) >= 1000 else 4, rungs)
    return found
