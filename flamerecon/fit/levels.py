"""Coarse-to-fine grids: the coarser grids ``grid.levels`` solved before ``grid.resolution``,
each warm-starting the next, and the iteration budget of each (``grid.level_iters``)."""

from __future__ import annotations

from collections.abc import Sequence

from flamerecon.errors import ConfigError
from flamerecon.geometry.grid import VoxelGrid


def level_grids(levels: Sequence | None, fine: VoxelGrid) -> list[VoxelGrid]:
    """The grids of ``levels`` (each an int: cells along the box's longest side, or
    [nx, ny, nz]) on the box of ``fine``, coarsest first. Each must be coarser than the next
    level and than ``fine``: no more cells along any axis and not the same grid; ConfigError
    naming ``grid.levels`` otherwise."""
    grids = []
    shown = [level if isinstance(level, (int, float)) else list(level) for level in levels or []]
    for level in shown:
        try:
            grids.append(VoxelGrid.from_box(fine.bbox_min, fine.bbox_max, level))
        except (ValueError, TypeError) as err:
            raise ConfigError(f"grid.levels: level {level}: {err}") from err
    for k, (a, b) in enumerate(zip(grids, [*grids[1:], fine])):
        if a.resolution == b.resolution or any(p > q for p, q in zip(a.resolution, b.resolution)):
            what = f"level {shown[k + 1]}" if k + 1 < len(grids) else "grid.resolution"
            mine, theirs = ("x".join(map(str, g.resolution)) for g in (a, b))
            raise ConfigError(
                f"grid.levels: level {shown[k]} ({mine} cells) is not coarser than {what} "
                f"({theirs} cells); list the levels coarsest first, each coarser than the next and "
                "than grid.resolution, e.g. grid.levels=[16,32] for grid.resolution=64"
            )
    return grids


def level_iters(value, n_levels: int) -> list[int | None]:
    """Iteration budget of each coarse level from ``grid.level_iters``: null (each keeps
    ``solver.max_iters``: None), one int for every level, or a list with one int per level."""
    if value is None:
        return [None] * n_levels
    values = [value] * n_levels if isinstance(value, int) else list(value)
    if len(values) != n_levels or not all(isinstance(v, int) and v > 0 for v in values):
        raise ConfigError(
            f"grid.level_iters: got {value}; give null, one positive int, or one positive int per "
            f"entry of grid.levels ({n_levels})"
        )
    return values
