"""A buoyant, incompressible smoke simulator on the reconstruction grid, in torch (differentiable
in the density, the velocity and the buoyancy: what assimilation fits through).

State: a density ``x`` (C, nz, ny, nx), the reconstruction's emission density, and a velocity
``u`` (3, nz, ny, nx) in cells per frame, components (x, y, z), at the cell centres. One step
is one frame of the capture (dt = 1 / frame rate seconds):

1. advection: x <- x(p - u(p)), u <- u(p - u(p)) (the velocity's own advection, unless
   ``self_advection`` is off), semi-Lagrangian (trilinear, the velocity held at the border, the
   density zero outside the grid) or MacCormack (a forward and a backward trace, the error
   corrected, clamped to the neighbourhood's range);
2. buoyancy: u <- u + buoyancy * (sum_c x) / peak * e_up, ``buoyancy`` the acceleration of the
   densest smoke in cells per frame^2 (``peak``: the first frame's channel-sum peak, so that the
   coefficient does not depend on the density's units), ``e_up`` the scene's up axis;
3. pressure projection (where ``incompressible``): u <- u - grad p with lap p = div u, a Leray projection in Fourier space
   on the box padded by ``pad`` cells of still air on each side (the wavenumbers of central
   differences, so the projected velocity's central-difference divergence is zero up to float
   precision away from the padding's wrap-around);
4. the source: in the inflow region (a mask (nz, ny, nx) in [0, 1]) the density is replaced by
   the source's density of that frame, x <- (1 - m) x + m s: the smoke re-injected.

In world units: a velocity of v cells per frame is v * cell size * frame rate world units per
second (metres per second where the scene's unit is the metre); the buoyancy b cells per frame^2
is b * cell size * frame rate^2 world units per second^2.

Why our own and not PhiFlow (measured in docs/results.md, "A simulator in the loop"): on the
reconstruction grid (85 x 128 x 85) one step here is a few grid_sample reads and two FFTs, and
autograd differentiates it through any number of steps; PhiFlow's staggered grid and
iterative pressure solve are the independent check (scripts/simulated_plume.py), not the loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import torch
import torch.nn.functional as F

from flamerecon.dynamics.conventions import heights
from flamerecon.geometry.axes import up_vector
from flamerecon.operators.warp import cell_points, sample_points

#: advection schemes
SCHEMES = ("semi_lagrangian", "maccormack")


def _traced(field: torch.Tensor, u: torch.Tensor, points: torch.Tensor, padding: str) -> torch.Tensor:
    """``field`` (C, nz, ny, nx) read at p - u(p) for every cell p (``points`` (3, P))."""
    return sample_points(field, points - u.reshape(3, -1), padding).reshape(field.shape)


def advect_field(field: torch.Tensor, u: torch.Tensor, scheme: str = "semi_lagrangian",
                 padding: str = "zeros") -> torch.Tensor:
    """``field`` (C, nz, ny, nx) carried one frame by ``u`` (3, nz, ny, nx), cells per frame
    (module doc, step 1); ``padding``: ``zeros`` for a density, ``border`` for a velocity."""
    shape = tuple(int(n) for n in field.shape[1:])
    points = cell_points(torch.arange(math.prod(shape), device=field.device), shape, u.dtype)
    ahead = _traced(field, u, points, padding)
    if scheme == "semi_lagrangian":
        return ahead
    back = _traced(ahead, -u, points, padding)  # the forward trace undone: its error is (back - field) / 2
    corrected = ahead + 0.5 * (field - back)
    lo = -F.max_pool3d(-field[None], 3, 1, 1)[0]  # the range of the cells the trace read from
    hi = F.max_pool3d(field[None], 3, 1, 1)[0]
    return torch.minimum(torch.maximum(corrected, _traced(lo, u, points, padding)), _traced(hi, u, points, padding))


def _wavenumbers(shape: tuple[int, int, int], device, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """sin(2 pi f) along x (rfft), y and z of a padded (nz, ny, nx) box: central differences' symbols."""
    nz, ny, nx = shape
    sx = torch.sin(2 * math.pi * torch.fft.rfftfreq(nx, device=device, dtype=dtype)).reshape(1, 1, -1)
    sy = torch.sin(2 * math.pi * torch.fft.fftfreq(ny, device=device, dtype=dtype)).reshape(1, -1, 1)
    sz = torch.sin(2 * math.pi * torch.fft.fftfreq(nz, device=device, dtype=dtype)).reshape(-1, 1, 1)
    return sx, sy, sz


def project(u: torch.Tensor, pad: int = 8) -> torch.Tensor:
    """The divergence-free part of ``u`` (3, nz, ny, nx) (module doc, step 3): u - grad p, p
    solving lap p = div u with central differences on the box padded by ``pad`` still cells
    on every side (periodic beyond them). Differentiable; a gradient field projects to zero."""
    shape = tuple(int(n) for n in u.shape[1:])
    padded = F.pad(u[None], (pad,) * 6)[0] if pad else u
    spectrum = torch.fft.rfftn(padded, dim=(1, 2, 3))
    sx, sy, sz = _wavenumbers(tuple(padded.shape[1:]), u.device, u.dtype)
    along = sx * spectrum[0] + sy * spectrum[1] + sz * spectrum[2]
    norm = sx ** 2 + sy ** 2 + sz ** 2
    scale = torch.where(norm > 1e-9, along / norm.clamp_min(1e-9), torch.zeros_like(along))
    spectrum = spectrum - torch.stack([sx * scale, sy * scale, sz * scale])
    out = torch.fft.irfftn(spectrum, s=tuple(padded.shape[1:]), dim=(1, 2, 3))
    if pad:
        out = out[:, pad:pad + shape[0], pad:pad + shape[1], pad:pad + shape[2]]
    return out


def central_divergence(u: torch.Tensor) -> torch.Tensor:
    """div u (nz-2, ny-2, nx-2) by central differences of one cell on the interior cells."""
    return 0.5 * ((u[0, 1:-1, 1:-1, 2:] - u[0, 1:-1, 1:-1, :-2]) + (u[1, 1:-1, 2:, 1:-1] - u[1, 1:-1, :-2, 1:-1])
                  + (u[2, 2:, 1:-1, 1:-1] - u[2, :-2, 1:-1, 1:-1]))


class Smoke:
    """The simulator's fixed parts: the grid ``shape`` (nz, ny, nx), the ``up`` axis, the
    ``buoyancy`` (cells per frame^2 at density ``peak``), the source ``region`` (nz, ny, nx) in
    [0, 1] (None: no source), the advection ``scheme``, the projection's ``pad``, whether the
    velocity is projected (``incompressible``) and advected by itself (``self_advection``)."""

    def __init__(self, shape: tuple[int, int, int], up: str, buoyancy: torch.Tensor | float, peak: float,
                 region: torch.Tensor | None = None, scheme: str = "semi_lagrangian", pad: int = 8,
                 incompressible: bool = True, self_advection: bool = True) -> None:
        if scheme not in SCHEMES:
            raise ValueError(f"scheme: got {scheme!r}; one of {SCHEMES}")
        self.shape, self.up, self.buoyancy, self.peak = tuple(shape), up, buoyancy, float(peak)
        self.region, self.scheme, self.pad, self.incompressible = region, scheme, int(pad), incompressible
        self.self_advection = self_advection

    def transport(self, x: torch.Tensor, u: torch.Tensor, source: torch.Tensor | None = None) -> torch.Tensor:
        """The density (C, nz, ny, nx) one frame on along a given velocity ``u`` (3, nz, ny, nx),
        cells per frame (projected first where the smoke is ``incompressible``), the source
        re-injected (steps 1 and 4 of the module doc, the velocity not evolved)."""
        if self.incompressible:
            u = project(u, self.pad)
        x = advect_field(x, u, self.scheme, "zeros")
        if source is not None and self.region is not None:
            x = x + self.region * (source - x)
        return x

    def step(self, x: torch.Tensor, u: torch.Tensor, source: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """One frame (module doc): (x, u) -> (x', u'); ``source`` (C, nz, ny, nx): the density
        injected in the region this frame (None: none)."""
        x_next = advect_field(x, u, self.scheme, "zeros")
        u_next = advect_field(u, u, self.scheme, "border") if self.self_advection else u
        direction = torch.tensor(up_vector(self.up), dtype=u.dtype, device=u.device).reshape(3, 1, 1, 1)
        u_next = u_next + self.buoyancy * (x_next.sum(0, keepdim=True) / self.peak) * direction
        if self.incompressible:
            u_next = project(u_next, self.pad)
        if source is not None and self.region is not None:
            x_next = x_next + self.region * (source - x_next)
        return x_next, u_next

    def run(self, x: torch.Tensor, u: torch.Tensor, steps: int,
            source: Callable[[int], torch.Tensor | None] | None = None) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """(x, u) after each of ``steps`` frames; ``source(n)``: the density injected at step
        n = 1, 2, ... (None: none)."""
        for n in range(1, int(steps) + 1):
            x, u = self.step(x, u, source(n) if source is not None else None)
            yield x, u


def carry(x: torch.Tensor, velocities: list[torch.Tensor], region: torch.Tensor | None = None,
          sources: list[torch.Tensor] | None = None) -> torch.Tensor:
    """``x`` (C, nz, ny, nx) carried along the velocities (3, nz, ny, nx) of successive frames
    (cells per frame), read once: every cell traced back through the last velocity, then the one
    before, ..., and the density read where the trace ends (a long horizon is not blurred by an
    interpolation per frame). Where a trace meets the source ``region`` after step n (going
    back), the cell takes ``sources[n - 1]`` there instead (the smoke injected then)."""
    shape = tuple(int(n) for n in x.shape[1:])
    points = cell_points(torch.arange(math.prod(shape), device=x.device), shape, velocities[0].dtype)
    value = torch.zeros(x.shape[0], points.shape[1], dtype=x.dtype, device=x.device)
    open_ = torch.ones(points.shape[1], dtype=torch.bool, device=x.device)
    for n in range(len(velocities), 0, -1):
        if region is not None and sources is not None:
            hit = open_ & (sample_points(region[None], points)[0] > 0.5)
            if bool(hit.any()):
                value[:, hit] = sample_points(sources[n - 1], points[:, hit]).to(x.dtype)
                open_ &= ~hit
        points = points - sample_points(velocities[n - 1], points, "border")
    value[:, open_] = sample_points(x, points[:, open_]).to(x.dtype)
    return value.reshape(x.shape)


def inflow_region(density: torch.Tensor, up: str, fraction: float, level: float = 0.05,
                  grow: int = 1) -> torch.Tensor:
    """(nz, ny, nx) in {0, 1}: the source region, the cells of the bottom ``fraction`` of the box
    along ``up`` where ``density``'s channel sum (C, nz, ny, nx) exceeds ``level`` of its peak
    there, grown by ``grow`` cells (within the bottom fraction)."""
    bottom = heights(tuple(density.shape[1:]), up, density.dtype).to(density.device) < fraction
    total = density.detach().sum(0) * bottom
    smoke = (total > level * float(total.max().clamp_min(1e-30))).to(density.dtype)
    if grow:
        smoke = F.max_pool3d(smoke[None, None], 2 * grow + 1, 1, grow)[0, 0]
    return smoke * bottom
