"""A capture's conventions as the dynamics read them: its up axis, its frame rate and its
length unit, in one place.

The flow, the simulator's buoyancy, the source region and the uniform shift follow :func:`up_of`;
velocities are given per second at :func:`frame_rate_of` and named by :func:`speed_unit`
("m/s" where the scene's unit is known to be the metre, else "world units/s"). Until the scene
carries these facts itself, they come from the options (``flow.up``, ``flow.frame_rate``) and
the scene's meta (``frame_rate``, ``frame_rates`` per camera, ``unit``).
"""

from __future__ import annotations

import torch

from flamerecon.errors import ConfigError
from flamerecon.scenes import Scene

#: the axes ``up`` may name
UP_AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")


def up_vector(up: str) -> tuple[float, float, float]:
    """The unit (x, y, z) of an axis of :data:`UP_AXES`."""
    sign = -1.0 if up.startswith("-") else 1.0
    axis = "xyz".index(up[-1])
    return tuple(sign if a == axis else 0.0 for a in range(3))  # type: ignore[return-value]


def heights(shape: tuple[int, int, int], up: str, dtype=torch.float64) -> torch.Tensor:
    """(nz, ny, nx): each cell centre's height in the grid along ``up``, 0 at the bottom
    cell, 1 at the top one (corner-aligned, as the control grids are)."""
    axis = 2 - "xyz".index(up[-1])
    n = shape[axis]
    h = torch.arange(n, dtype=dtype) / max(n - 1, 1)
    if up.startswith("-"):
        h = 1 - h
    view = [1, 1, 1]
    view[axis] = n
    return h.reshape(view).expand(shape)


def up_of(scene: Scene | None, given: str | None = None) -> str:
    """The scene's up axis ("x", "-y", ...): ``given`` (an option) where set, else the
    scene's, else y."""
    if given is not None:
        return given.removeprefix("+")
    found = getattr(scene, "up", None) if scene is not None else None
    return str(found).removeprefix("+") if found else "y"


def frame_rate_of(scene: Scene | None, given: float | None = None, where: str = "flow.frame_rate") -> float | None:
    """Frames per second: ``given`` where set, else the scene's (None: unknown). Cameras that
    disagree are refused, naming their rates: one velocity cannot hold two clocks."""
    if given is not None:
        return float(given)
    if scene is None:
        return None
    found = getattr(scene, "frame_rate", None)
    if found is None:
        found = scene.meta.get("frame_rate")
    rates = scene.meta.get("frame_rates") or {}
    if found is None and len(set(rates.values())) > 1:
        listed = ", ".join(f"{name} {rate:g}" for name, rate in rates.items())
        raise ConfigError(f"{where}: the cameras run at different frame rates ({listed} frames per second); "
                          f"a velocity needs one clock: give {where}=FRAMES_PER_SECOND, or resample the videos "
                          "to one rate")
    return None if found is None else float(found)


def metres_per_unit(scene: Scene | None) -> float | None:
    """The scene's length unit in metres (None: not known)."""
    if scene is None:
        return None
    found = getattr(scene, "unit", None)
    if found is None:
        found = scene.meta.get("unit")
    return None if found is None else float(found)


def speed_unit(scene: Scene | None) -> str:
    """How a velocity per second is named: "m/s" where the scene's unit is one metre, else
    "world units/s"."""
    return "m/s" if metres_per_unit(scene) == 1.0 else "world units/s"
