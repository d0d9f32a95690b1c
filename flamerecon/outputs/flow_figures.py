"""Pictures of a velocity field beside its density (matplotlib): slices of the speed with arrows
and of the vorticity through the plume, and streamlines over the plume's projection.

Inputs are numpy arrays on one grid: the density (C, nz, ny, nx), the velocity (3, nz, ny, nx)
in world units per second (components x, y, z), the box ``bbox_min``/``bbox_max`` and the
scene's ``up`` axis: the figures are drawn with ``up`` upwards (the volume turned by the signed
permutation of :func:`~flamerecon.geometry.axes.turn_from_y`), each axis labelled with the world
axis it shows (``-z`` where the turned x is the world's -z).
Every figure returns an (H, W, 3) uint8 image (:func:`flamerecon.outputs.figures.write_png`
writes it).
"""

from __future__ import annotations

import numpy as np
import torch

from flamerecon.geometry.axes import axis_name, turn_box, turn_from_y, turn_volume
from flamerecon.operators.warp import curl
from flamerecon.outputs.export import voxel_size
from flamerecon.outputs.figures import centroid_index

_HINT = "pip install 'flamerecon[figures]'"
def _figure(width: float, height: float):
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError(f"velocity figures need matplotlib; {_HINT}") from err
    return Figure(figsize=(width, height), dpi=100)


def _rgb(fig) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.ascontiguousarray(np.asarray(canvas.buffer_rgba())[..., :3])


def smoke_only(field: np.ndarray, density: np.ndarray, level: float = 0.01, grow: int = 2) -> np.ndarray:
    """``field`` (..., nz, ny, nx) with NaN where the density (nz, ny, nx) stays below ``level``
    of its peak within ``grow`` cells: a velocity is only measured where smoke moves."""
    import torch.nn.functional as F

    mask = torch.from_numpy(density > level * density.max()).float()[None, None]
    near = F.max_pool3d(mask, 2 * grow + 1, 1, grow)[0, 0].numpy() > 0
    return np.where(near, field, np.nan)


def vorticity_world(velocity: np.ndarray, bbox_min, bbox_max) -> np.ndarray:
    """curl of a velocity (3, nz, ny, nx) in world units per second: (3, nz, ny, nx) in 1/s."""
    size = voxel_size(bbox_min, bbox_max, velocity.shape)
    return curl(torch.from_numpy(np.asarray(velocity, dtype=np.float64)), tuple(size.tolist())).numpy()


def upright(density: np.ndarray, velocity: np.ndarray, bbox_min, bbox_max, up: str):
    """The density (C, ...) and velocity (3, ...) turned so that ``up`` points along +y, their
    box, and the names of the world axes the turned x, y and z show ("+x", "-z", ...)."""
    Q = turn_from_y(axis_name(up) or "+y").T  # up -> +y
    dens = turn_volume(torch.from_numpy(np.ascontiguousarray(density)), Q).numpy()
    vel = turn_volume(torch.from_numpy(np.ascontiguousarray(velocity)), Q)
    vel = torch.einsum("ij,j...->i...", Q.to(vel.dtype), vel).numpy()
    lo, hi = turn_box(tuple(np.asarray(bbox_min, float)), tuple(np.asarray(bbox_max, float)), Q)
    names = []
    for a in range(3):  # the world direction of turned axis a: column a of Q^T
        axis = int(Q[a].abs().argmax())
        names.append(("-" if float(Q[a, axis]) < 0 else "+") + "xyz"[axis])
    return dens, vel, np.asarray(lo), np.asarray(hi), names


def _planes(density: np.ndarray, velocity: np.ndarray, bbox_min, bbox_max, names: list[str]):
    """The three slices through the density's centre of mass: (title, horizontal axis,
    vertical axis, slice index function, in-plane components, out-of-plane component, extent)."""
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    i, j, k = centroid_index(density)
    size = voxel_size(lo, hi, density.shape)
    centre = lo + (np.array([i, j, k]) + 0.5) * size
    return [
        (f"front slice, {names[2]} = {centre[2]:.3f}", 0, 1, lambda a: a[..., k, :, :], (0, 1), 2,
         (lo[0], hi[0], lo[1], hi[1])),
        (f"side slice, {names[0]} = {centre[0]:.3f}", 2, 1, lambda a: np.swapaxes(a[..., :, :, i], -1, -2), (2, 1), 0,
         (lo[2], hi[2], lo[1], hi[1])),
        (f"horizontal slice, {names[1]} = {centre[1]:.3f}", 0, 2, lambda a: a[..., :, j, :], (0, 2), 1,
         (lo[0], hi[0], lo[2], hi[2])),
    ]


def velocity_slices_figure(density, velocity, bbox_min, bbox_max, title: str = "", length_unit: str = "m",
                           arrows: int = 16, up: str = "+y") -> np.ndarray:
    """Two rows of three slices through the density's centre of mass (front, side and
    horizontal, ``up`` upwards in the first two): the speed with the in-plane velocity as arrows (about ``arrows`` along a
    side) and the smoke's outline (10 % of the slice's peak density), then the vorticity
    component normal to the slice (1/s, red anticlockwise seen from +axis); blank where there
    is no smoke (:func:`smoke_only`)."""
    density, velocity, bbox_min, bbox_max, names = upright(np.asarray(density, dtype=np.float64),
                                                           np.asarray(velocity, dtype=np.float64), bbox_min,
                                                           bbox_max, up)
    density = density.sum(0)
    omega = smoke_only(vorticity_world(velocity, bbox_min, bbox_max), density)
    speed = np.linalg.norm(velocity, axis=0)
    velocity, speed = smoke_only(velocity, density), smoke_only(speed, density)
    fig = _figure(15.0, 9.5)
    planes = _planes(density[None], velocity, bbox_min, bbox_max, names)
    top = float(np.nanpercentile(speed, 99)) if np.isfinite(speed).any() else 1.0
    vort = max(float(np.nanpercentile(np.abs(omega), 99)) if np.isfinite(omega).any() else 1.0, 1e-12)
    for col, (name, h, v, cut, inplane, normal, extent) in enumerate(planes):
        dens = cut(density)
        rows, cols = dens.shape
        grid = (np.linspace(extent[0], extent[1], cols), np.linspace(extent[2], extent[3], rows))
        axes = (f"{names[h]} [{length_unit}]", f"{names[v]}{' (up)' if v == 1 else ''} [{length_unit}]")
        ax = _panel(fig, col + 1, cut(speed), extent, dens, ("viridis", 0, max(top, 1e-12)), "orange",
                    f"speed, {name}", axes, f"speed [{length_unit}/s]")
        step = max(1, max(rows, cols) // arrows)
        ax.quiver(grid[0][::step], grid[1][::step], cut(velocity[inplane[0]])[::step, ::step],
                  cut(velocity[inplane[1]])[::step, ::step], color="white", scale_units="xy", angles="xy",
                  scale=None, width=0.004)
        _panel(fig, col + 4, cut(omega[normal]), extent, dens, ("RdBu_r", -vort, vort), "black",
               f"vorticity {names[normal]}-component, {name}", axes, "vorticity [1/s]")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _rgb(fig)


def _panel(fig, at: int, image: np.ndarray, extent, dens: np.ndarray, colours: tuple, outline: str, title: str,
           axes: tuple[str, str], bar: str):
    """Subplot ``at`` of a 2 x 3 figure: ``image`` (rows, cols) over ``extent`` in the colour map and
    range ``colours``, the smoke's outline (10 % of ``dens``'s peak), titles and a colour bar."""
    ax = fig.add_subplot(2, 3, at)
    cmap, low, high = colours
    im = ax.imshow(image, origin="lower", extent=extent, cmap=cmap, vmin=low, vmax=high)
    if dens.max() > 0:
        rows, cols = dens.shape
        ax.contour(np.linspace(extent[0], extent[1], cols), np.linspace(extent[2], extent[3], rows), dens,
                   levels=[0.1 * dens.max()], colors=outline, linewidths=0.8)
    ax.set_title(title)
    ax.set_xlabel(axes[0])
    ax.set_ylabel(axes[1])
    fig.colorbar(im, ax=ax, label=bar, shrink=0.85)
    return ax


def streamlines_figure(density, velocity, bbox_min, bbox_max, title: str = "", length_unit: str = "m",
                       up: str = "+y") -> np.ndarray:
    """The smoke seen from the front and from the side (``up`` upwards), each with the
    streamlines of the in-plane velocity on the slice through its centre of mass, coloured by
    speed, where there is smoke (:func:`smoke_only`)."""
    dens, velocity, lo, hi, names = upright(np.asarray(density, dtype=np.float64),
                                            np.asarray(velocity, dtype=np.float64), bbox_min, bbox_max, up)
    dens = dens.sum(0)
    velocity = smoke_only(velocity, dens)
    speed = np.linalg.norm(velocity, axis=0)
    size = voxel_size(lo, hi, velocity.shape)
    i, _, k = centroid_index(dens[None])
    nz, ny, nx = dens.shape
    centres = [lo[a] + (np.arange(n) + 0.5) * size[a] for a, n in enumerate((nx, ny, nz))]
    top = float(np.nanpercentile(speed, 99)) if np.isfinite(speed).any() else 1.0
    fig = _figure(11.0, 7.5)
    views = [(f"front (along {names[2]}), streamlines at {names[2]} of the centre", dens.sum(0),
              centres[0], velocity[0][k], velocity[1][k], speed[k], names[0]),
             (f"side (along {names[0]}), streamlines at {names[0]} of the centre", dens.sum(2).T,
              centres[2], velocity[2][:, :, i].T, velocity[1][:, :, i].T, speed[:, :, i].T, names[2])]
    for col, (name, picture, horizontal, uh, uv, sp, axis) in enumerate(views):
        ax = fig.add_subplot(1, 2, col + 1)
        ax.imshow(picture, origin="lower", cmap="gray",
                  extent=(horizontal[0] - size[0] / 2, horizontal[-1] + size[0] / 2, lo[1], hi[1]))
        lines = ax.streamplot(horizontal, centres[1], np.ma.masked_invalid(uh), np.ma.masked_invalid(uv),
                              color=np.ma.masked_invalid(sp), cmap="plasma", density=1.4, linewidth=0.9,
                              arrowsize=0.8, norm=_norm(0, max(top, 1e-12)))
        ax.set_xlim(horizontal[0], horizontal[-1])
        ax.set_ylim(lo[1], hi[1])
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(f"{axis} [{length_unit}]")
        ax.set_ylabel(f"{names[1]} (up) [{length_unit}]")
        fig.colorbar(lines.lines, ax=ax, label=f"speed [{length_unit}/s]", shrink=0.85)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _rgb(fig)


def _norm(lo: float, hi: float):
    from matplotlib.colors import Normalize

    return Normalize(lo, hi)
