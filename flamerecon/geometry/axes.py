"""A capture's up axis, named as its owner names it: ``"+x"``, ``"-x"``, ``"+y"``, ``"-y"``,
``"+z"`` or ``"-z"`` (world axes of the calibration), and the one the cameras suggest.

Every figure, orbit camera and flow that needs "up" takes one of these names (a scene's
``up``), so that nothing assumes y.
"""

from __future__ import annotations

import math

import numpy as np
import torch

#: the names an up axis may have, normalised (a bare ``"y"`` reads as ``"+y"``)
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
#: a camera rig whose image-up directions spread wider than this about their mean axis does not
#: say which way is up (degrees between the mean direction and the nearest world axis)
AUTO_UP_TOLERANCE_DEG = 30.0


def axis_name(value) -> str | None:
    """``value`` as one of :data:`UP_AXES` (``"y"``, ``"+Y"`` and ``"+y"`` alike), or None when
    it names no axis."""
    if not isinstance(value, str):
        return None
    text = value.strip().lower()
    if text in ("x", "y", "z"):
        text = "+" + text
    return text if text in UP_AXES else None


def axis_index(up: str) -> int:
    """The world axis of ``up`` (one of :data:`UP_AXES`): 0 for x, 1 for y, 2 for z."""
    return "xyz".index(up[-1])


def axis_sign(up: str) -> float:
    """+1.0 or -1.0: whether ``up`` points along its axis or against it."""
    return -1.0 if up.startswith("-") else 1.0


def up_vector(up: str) -> tuple[float, float, float]:
    """The unit world vector (x, y, z) of ``up``."""
    vector = [0.0, 0.0, 0.0]
    vector[axis_index(up)] = axis_sign(up)
    return tuple(vector)


def image_up_directions(world_to_camera: torch.Tensor) -> torch.Tensor:
    """(B, 3): the world direction each camera shows upwards in its image (its negative
    y axis, OpenCV frame), from OpenCV world->camera matrices (B, 4, 4)."""
    return -world_to_camera[:, 1, :3].double()


def up_from_cameras(world_to_camera: torch.Tensor) -> tuple[str | None, float]:
    """The world axis the cameras show upwards on average, and the angle (degrees) between
    that mean direction and the axis: (axis, angle), or (None, angle) when the rig does not
    agree on one: the mean of the unit directions is shorter than the cosine of
    :data:`AUTO_UP_TOLERANCE_DEG` (directions spread or opposed; the angle is then their
    spread's), or it lies further than that from every axis.

    Only the images' orientation speaks here: a rig whose images show the flame upside down
    (a camera mounted on its head) gives the opposite axis; the capture must then say its up."""
    mean = torch.nn.functional.normalize(image_up_directions(world_to_camera), dim=1).mean(0)
    norm = float(mean.norm())
    if norm < math.cos(math.radians(AUTO_UP_TOLERANCE_DEG)):  # directions spread wide or opposed
        return None, math.degrees(math.acos(min(1.0, norm)))
    mean = mean / norm
    index = int(mean.abs().argmax())
    angle = math.degrees(math.acos(min(1.0, abs(float(mean[index])))))
    if angle > AUTO_UP_TOLERANCE_DEG:
        return None, angle
    return ("-" if float(mean[index]) < 0 else "+") + "xyz"[index], angle


def ground_axes(up: str) -> tuple[int, int]:
    """The two world axes across ``up`` (indices, in x, y, z order): the ground plane's."""
    return tuple(i for i in range(3) if i != axis_index(up))


#: the proper rotation (a signed permutation) carrying +y onto each up axis
_TURNS = {
    "+y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "+z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "-z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "+x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
    "-x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
}


def turn_from_y(up: str) -> torch.Tensor:
    """(3, 3) float64 Q, a rotation that permutes the axes (with signs) and carries +y onto
    ``up``: a world built y-up (a synthetic scene) turned to rise along ``up`` is x' = Q x."""
    return torch.tensor(_TURNS[up], dtype=torch.float64)


def turn_box(lo, hi, Q: torch.Tensor) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The axis-aligned box (lo, hi) turned by the signed permutation ``Q``."""
    a = Q @ torch.tensor(lo, dtype=torch.float64)
    b = Q @ torch.tensor(hi, dtype=torch.float64)
    return tuple(torch.minimum(a, b).tolist()), tuple(torch.maximum(a, b).tolist())


def turn_volume(volume: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
    """A volume (..., nz, ny, nx) on an axis-aligned grid, as seen on the grid of the box
    turned by the signed permutation ``Q`` (:func:`turn_box`): axes permuted and flipped."""
    lead = volume.ndim - 3
    dim = {0: lead + 2, 1: lead + 1, 2: lead}  # world axis -> array dimension (x fastest)
    order, flips = [], []
    for new in (2, 1, 0):  # the new array's dimensions: z, y, x
        old = int(Q[new].abs().argmax())
        order.append(dim[old])
        if float(Q[new, old]) < 0:
            flips.append(lead + len(order) - 1)
    turned = volume.permute(*range(lead), *order)
    return turned.flip(flips) if flips else turned


def ground_directions(up: str) -> tuple[tuple[int, float], tuple[int, float]]:
    """The two signed world axes across ``up`` that a figure shows as its horizontal and its
    second direction ((axis index, +-1.0) each): +y's x and z, carried by :func:`turn_from_y`,
    so that a scene turned to another up draws the same pictures (top view, slices, orbits)."""
    Q = turn_from_y(up)
    out = []
    for column in (0, 2):  # the images of +x and +z
        axis = int(Q[:, column].abs().argmax())
        out.append((axis, float(Q[axis, column])))
    return out[0], out[1]


def azimuth_zero(up: np.ndarray) -> np.ndarray:
    """The world direction (3,) of azimuth 0 about the unit vector ``up``: for up within a
    degree of a world axis, +z turned by :func:`turn_from_y` (+z for +y, -y for +z), so a
    turned scene's orbits and angles are the same; else the world axis most perpendicular to
    ``up`` (ties to z, then x, then y). Not flattened onto the ground."""
    up = np.asarray(up, np.float64)
    index = int(np.abs(up).argmax())
    if abs(up[index]) > math.cos(math.radians(1.0)):
        return turn_from_y(("+" if up[index] > 0 else "-") + "xyz"[index]).numpy()[:, 2].copy()
    return np.eye(3)[min((2, 0, 1), key=lambda a: abs(up[a]))]


def ground_frame(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (3,) of azimuth 0 and 90 degrees about ``up`` (3,): :func:`azimuth_zero`
    flattened onto the ground, and ``up x`` it (azimuths count counter-clockwise seen from above)."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    first = azimuth_zero(up)
    first = first - (first @ up) * up
    first = first / np.linalg.norm(first)
    return first, np.cross(up, first)


def world_angles(offsets: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth in [0, 360), elevation) in degrees of the directions ``offsets`` (N, 3) about
    ``up`` (3,), azimuth from :func:`ground_frame`'s first direction towards its second."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    first, second = ground_frame(up)
    d = np.asarray(offsets, np.float64).reshape(-1, 3)
    azimuth = np.degrees(np.arctan2(d @ second, d @ first)) % 360.0
    elevation = np.degrees(np.arcsin(np.clip((d @ up) / np.linalg.norm(d, axis=1).clip(1e-12), -1, 1)))
    return azimuth, elevation
