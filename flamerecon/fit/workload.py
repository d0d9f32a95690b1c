"""What a reconstruction will cost, told before the work: its rays (every view's pixels whose
ray crosses the box), voxels, ray samples per pass, memory and a rough time. Huge images on a
tiny grid used to run silently for minutes: :func:`check_workload` logs the estimate (one INFO
line), refuses what clearly exceeds the memory available and warns when the time is long."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from flamerecon.errors import MemoryBudgetError
from flamerecon.fit.checks import DENSE_BYTES_PER_VOXEL, check_grid_memory, memory_budget
from flamerecon.fit.memory import format_bytes
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.geometry.cameras import pixel_rays
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import (
    BYTES_PER_NNZ_PEAK,
    NNZ_PER_SAMPLE,
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
BYTES_PER_RAY_CHANNEL = 24
#: seconds per ray sample (and channel) on two busy CPU cores, measured on the synthetic preset
#: and a 16^3 march: assembling the operator; one pass (forward or adjoint) of the assembled
#: operator per channel; of the matrix-free one. Rough; no time is estimated on CUDA (not measured).
ASSEMBLY_SECONDS = 1.5e-7
ASSEMBLED_PASS_SECONDS = 2.5e-10
MATRIX_FREE_PASS_SECONDS = 7e-8
#: an estimated time from which the estimate is a WARNING, not an INFO line
LONG_SECONDS = 300.0


@dataclass(frozen=True)
class Workload:
    rays: int  # pixels of every view whose ray crosses the box
    voxels: int
    samples: int  # ray samples of one pass over them
    passes: int  # forward and adjoint passes of the solve, and one to score
    ray_bytes: int
    voxel_bytes: int
    seconds: float | None  # None: not estimated (CUDA)

    @property
    def bytes(self) -> int:
        return self.ray_bytes + self.voxel_bytes

    def __str__(self) -> str:
        time = "time not estimated" if self.seconds is None else f"{duration(self.seconds)}"
        return (f"{self.rays:.3g} rays, {self.voxels:.3g} voxels, {self.samples:.3g} ray samples per pass: "
                f"about {format_bytes(self.bytes)} of memory and {time} for {self.passes} passes")


def duration(seconds: float) -> str:
    """``95.0`` -> ``'1.6 min'``."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, device: torch.device) -> Workload:
    """The estimate for ``scene`` on ``grid``: each view's share of rays crossing the box and
    their mean chord, measured on a lattice of :data:`LATTICE`\\ ² pixels, scaled to its
    pixels; ``solver.max_iters`` forward and adjoint passes and one to score, through the
    assembled operator when it would fit (else matrix-free, slower per pass)."""
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
    passes = 2 * int(options.solver.params.get("max_iters", 500)) + 1
    ray_bytes = rays * (BYTES_PER_RAY + BYTES_PER_RAY_CHANNEL * C)
    voxel_bytes = grid.num_voxels * (DENSE_BYTES_PER_VOXEL + scene.num_views)
    budget = memory_budget(device, options.projector.max_memory_gb)
    assembled = options.projector.backend != "matrix_free" and (
        budget is None or samples * NNZ_PER_SAMPLE * (16 + BYTES_PER_NNZ_PEAK) <= budget)
    seconds = (samples * (ASSEMBLY_SECONDS + C * passes * ASSEMBLED_PASS_SECONDS) if assembled
               else samples * C * passes * MATRIX_FREE_PASS_SECONDS)
    return Workload(rays, grid.num_voxels, samples, passes, ray_bytes, voxel_bytes,
                    None if device.type == "cuda" else seconds)


def check_workload(scene: Scene, options: ReconstructionOptions, grid: VoxelGrid, device: torch.device) -> Workload:
    """Log :func:`workload` (INFO; WARNING from :data:`LONG_SECONDS`), and refuse one whose
    memory exceeds the budget (``projector.max_memory_gb``, else most of what ``device`` has
    free) with the settings that shrink it."""
    budget = memory_budget(device, options.projector.max_memory_gb)
    check_grid_memory(grid, scene.num_views, device, budget)  # the grid alone: its own message
    found = workload(scene, options, grid, device)
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
    if found.seconds is not None and found.seconds >= LONG_SECONDS:
        log.warning("estimate: %s on %s, a long run; a larger scene.downscale, a smaller grid.resolution or fewer "
                    "solver.max_iters make it shorter", found, device)
    else:
        log.info("estimate: %s on %s", found, device)
    return found
