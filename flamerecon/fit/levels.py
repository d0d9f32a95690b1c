"""Coarse-to-fine: the solves before the run's own, each warm-starting the next.

Two kinds of level, in this order:

- the resolution ladder (``ladder.rungs``): coarser images *and* grids, ``(downscale, grid
  resolution)`` pairs, each solved on the capture loaded at that downscale (as
  ``scene.downscale`` loads it). Only the rungs whose downscale is above the run's own run, so
  one preset serves every resolution: ScalarFlow's ``[[4, 128], [2, 192]]`` adds nothing to a
  run at 1/4 and both rungs to one at full resolution. The camera fit runs on the coarsest
  rung's images and the cameras carry over to every level (their intrinsics scaled with the
  image size), so a capture's calibration file from a run at 1/4 serves a full-resolution run;
- coarser grids on the run's own images (``grid.levels``, iteration budgets ``grid.level_iters``).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

from flamerecon.arguments import wrong_value
from flamerecon.errors import ConfigError
from flamerecon.fit.option_rules import check_section
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.scenes import Scene


@dataclass(frozen=True)
class LadderOptions:
    """``rungs``: ((downscale, grid resolution), ...) coarsest first, solved before the run's
    own images and grid where their downscale is above the scene's; ``iterations``: the
    solver's ``max_iters`` on each rung that runs (None: the solver's, an int, or one per rung);
    ``final_iterations``: the solver's ``max_iters`` on the run's own level after a rung ran
    (None: the solver's)."""

    rungs: tuple = ()
    iterations: int | tuple | None = None
    final_iterations: int | None = None

    def __post_init__(self) -> None:
        check_section("ladder", self)
        factors = [int(d) for d, _ in self.rungs]
        if any(a <= b for a, b in itertools.pairwise(factors)):
            raise wrong_value("ladder.rungs", self.rungs, "rungs whose downscales decrease, coarsest first "
                              "(e.g. [[4, 128], [2, 192]])")
        if isinstance(self.iterations, tuple) and len(self.iterations) != len(self.rungs):
            raise wrong_value("ladder.iterations", self.iterations, f"null, one int, or one per rung of "
                              f"ladder.rungs ({len(self.rungs)})")


@dataclass(frozen=True)
class Level:
    """A solve before the run's own: its ``grid``, the ``downscale`` of its images (None: the
    run's own) and its iteration budget (None: the solver's ``max_iters``)."""

    grid: VoxelGrid
    downscale: int | None
    iters: int | None

    def plan_entry(self) -> list[int]:
        """[nx, ny, nz], and the downscale after them for a rung (checkpoints compare plans)."""
        return [*self.grid.resolution, *([] if self.downscale is None else [self.downscale])]


def scene_downscale(scene: Scene) -> int | None:
    """The downscale a scene was loaded at (``scene.downscale``, 1 when not given); None for a
    scene not made by :func:`flamerecon.scenes.load_scene` (its other resolutions are unknown)."""
    config = scene.meta.get("config")
    return None if config is None else int(config.get("downscale") or 1)


def ladder_rungs(scene: Scene, ladder: LadderOptions, fine: VoxelGrid) -> list[Level]:
    """The rungs of ``ladder`` that run for ``scene`` (downscale above the scene's), coarsest
    first, on the box of ``fine``; a ConfigError when one would need to reload a scene that
    :func:`~flamerecon.scenes.load_scene` did not make."""
    own = scene_downscale(scene)
    wanted = [(int(d), res) for d, res in ladder.rungs if own is None or int(d) > own]
    if not wanted:
        return []
    if own is None:
        raise ConfigError("ladder.rungs: this scene was not loaded by load_scene, so it cannot be loaded at "
                          "another downscale; set ladder.rungs=[] or load it with flamerecon.load_scene")
    budgets = ladder.iterations if isinstance(ladder.iterations, tuple) else (ladder.iterations,) * len(ladder.rungs)
    budget = {int(d): b for (d, _), b in zip(ladder.rungs, budgets)}
    levels = []
    for d, res in wanted:
        try:
            grid = VoxelGrid.from_box(fine.bbox_min, fine.bbox_max, res if isinstance(res, int) else list(res))
        except (ValueError, TypeError) as err:
            raise ConfigError(f"ladder.rungs: rung [{d}, {res}]: {err}") from err
        if any(p > q for p, q in zip(grid.resolution, fine.resolution)):
            mine, theirs = ("x".join(map(str, g.resolution)) for g in (grid, fine))
            raise ConfigError(
                f"ladder.rungs: rung [{d}, {res}] ({mine} cells) is finer than the run's own grid ({theirs} cells, "
                f"grid.resolution); a rung solves a coarser problem first: give grid.resolution at least {res}, or "
                f"drop the rung (ladder.rungs=[...] without it; ladder.rungs=[] for no ladder)")
        levels.append(Level(grid, d, budget[d]))
    return levels


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


def plan_levels(scene: Scene, ladder: LadderOptions, levels: Sequence | None, level_budget,
                fine: VoxelGrid) -> list[Level]:
    """Every solve before the run's own, in order: the ladder's rungs that run for ``scene``
    (:func:`ladder_rungs`), then the coarser grids ``levels`` on the run's images with their
    budgets ``level_budget`` (``grid.level_iters``)."""
    grids = level_grids(levels, fine)
    budgets = level_iters(level_budget, len(grids))
    return [*ladder_rungs(scene, ladder, fine), *(Level(g, None, b) for g, b in zip(grids, budgets))]
