"""A capture's conventions as the dynamics read them: its up axis, its frame rate and its
length unit, each a scene fact (:class:`~flamerecon.scenes.base.Scene` ``up``, ``frame_rate``,
``unit``, read once by the loaders), overridden by an option where one is given.

The flow, the simulator's buoyancy, the source region and the uniform shift follow :func:`up_of`;
velocities are given per second at :func:`frame_rate_of` and named by :func:`speed_unit` ("m/s"
where the scene's unit is the metre, "cm/s", "mm/s", else "world units/s").
"""

from __future__ import annotations

import torch

from flamerecon.geometry.axes import axis_index, axis_name
from flamerecon.geometry.units import length_name
from flamerecon.scenes import Scene


def up_of(scene: Scene | None, given: str | None = None) -> str:
    """The up axis ("+x", "-y", ...): ``given`` (an option) where set, else the scene's, else +y."""
    if given is not None:
        return axis_name(given) or given
    return scene.up if scene is not None else "+y"


def frame_rate_of(scene: Scene | None, given: float | None = None) -> float | None:
    """Frames per second: ``given`` where set, else the scene's (None: unknown)."""
    if given is not None:
        return float(given)
    return None if scene is None else scene.frame_rate


def speed_unit(scene: Scene | None) -> str:
    """How a velocity per second is named: the scene's length unit per second ("m/s", "mm/s",
    ...; "world units/s" where the scene does not give its unit)."""
    return f"{length_name(None if scene is None else scene.unit)}/s"


def heights(shape: tuple[int, int, int], up: str, dtype=torch.float64) -> torch.Tensor:
    """(nz, ny, nx): each cell centre's height in the grid along ``up``, 0 at the bottom
    cell, 1 at the top one (corner-aligned, as the control grids are)."""
    axis = 2 - axis_index(up)
    n = shape[axis]
    h = torch.arange(n, dtype=dtype) / max(n - 1, 1)
    if up.startswith("-"):
        h = 1 - h
    view = [1, 1, 1]
    view[axis] = n
    return h.reshape(view).expand(shape)
