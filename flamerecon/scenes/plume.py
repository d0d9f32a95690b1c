"""A synthetic smoke plume carried by a known divergence-free velocity: the check of a fitted flow.

A textured column of smoke (world units; y up, inside the box x, z in [-0.5, 0.5], y in
[0, 1.5]) rises and swirls in the steady velocity

    u(p) = (-omega(r) (z - cz), w(r), omega(r) (x - cx)),   r = |(x - cx, z - cz)|,
    omega(r) = swirl * g(r),  w(r) = rise * (0.6 + 0.4 g(r)),  g(r) = exp(-r^2 / (2 * 0.15^2)),

a rotation about the vertical axis through (cx, cz) whose rate falls off with r, over an
updraught strongest on the axis: divergence-free (no term depends on the coordinate it is
differentiated by, and the swirl is tangential), in world units per second. Every point moves on
a helix of constant r, so frame t's density is the frame-0 density read at the point the flow
carried there, exactly: rho_t(p) = rho_0(R(-omega(r) t) p - w(r) t e_y), t = frame / 30 s. The
images are rendered from a phantom finer than any reconstruction (``phantom_resolution``) by a
ring of ``n_cameras`` cameras (the last held out), plus sensor noise, as the synthetic flame's
(:mod:`flamerecon.scenes.synthetic`). :func:`true_velocity` gives the velocity on any grid.

Config (``scene`` node): ``n_cameras``, ``width``, ``height``, ``frame``, ``seed`` (the smoke's
texture), ``phantom_resolution``, ``noise``, ``peak``, ``rise`` (world units per second on the
axis), ``swirl`` (radians per second on the axis).
"""

from __future__ import annotations

import sys

import torch

from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.scenes import register_scene
from flamerecon.scenes.base import Scene
from flamerecon.scenes.cache import cached
from flamerecon.scenes.synthetic import (
    BOX_MAX,
    BOX_MIN,
    SECONDS_PER_FRAME,
    _crop_to_support,
    _noise,
    ring_cameras,
)
from flamerecon.scenes.values import NONNEGATIVE, POSITIVE, read_float, read_int

_RENDER_CODE = ("flamerecon.scenes.plume", "flamerecon.scenes.synthetic", "flamerecon.operators.projector",
                "flamerecon.geometry.grid", "flamerecon.geometry.cameras")
#: the plume's axis (x, z) and the width of its swirl and updraught (world units)
AXIS = (0.0, 0.0)
CORE = 0.15
RISE = 0.6
SWIRL = 2.0


def _profile(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(dx, dz, g(r)) of world points (..., 3) about the axis."""
    dx, dz = points[..., 0] - AXIS[0], points[..., 2] - AXIS[1]
    return dx, dz, torch.exp(-(dx ** 2 + dz ** 2) / (2 * CORE ** 2))


def plume_velocity(points: torch.Tensor, rise: float = RISE, swirl: float = SWIRL) -> torch.Tensor:
    """The velocity (..., 3), world units per second, at world points (..., 3) (module doc)."""
    dx, dz, g = _profile(points)
    omega = swirl * g
    return torch.stack([-omega * dz, rise * (0.6 + 0.4 * g), omega * dx], -1)


def plume_density(points: torch.Tensor, seconds: float, seed: int = 0, rise: float = RISE,
                  swirl: float = SWIRL) -> torch.Tensor:
    """The smoke density (...,) at world points (..., 3) after ``seconds`` of the flow: the
    frame-0 plume read where each point came from."""
    dx, dz, g = _profile(points)
    angle = -swirl * g * seconds  # rotate back along the helix
    c, s = torch.cos(angle), torch.sin(angle)
    x0 = AXIS[0] + c * dx - s * dz
    z0 = AXIS[1] + s * dx + c * dz
    y0 = points[..., 1] - rise * (0.6 + 0.4 * g) * seconds
    start = torch.stack([x0, y0, z0], -1)
    r2 = (x0 - AXIS[0]) ** 2 + (z0 - AXIS[1]) ** 2
    column = torch.exp(-r2 / (2 * 0.12 ** 2)) * torch.sigmoid((y0 - 0.15) / 0.03) * torch.sigmoid((0.75 - y0) / 0.05)
    texture = (0.55 + 0.45 * _noise(start * 3.0, seed + 11)).clamp_min(0)
    return column * texture


def true_velocity(grid: VoxelGrid, rise: float = RISE, swirl: float = SWIRL, units: str = "cells",
                  frame_rate: float = 1.0 / SECONDS_PER_FRAME) -> torch.Tensor:
    """The plume's velocity (3, nz, ny, nx) at the cell centres of ``grid``: ``world`` units per
    second, or ``cells`` per frame (divided by the cell size and the frame rate)."""
    u = plume_velocity(grid.centers(), rise, swirl).permute(3, 0, 1, 2).contiguous()
    if units == "world":
        return u
    return u / (grid.voxel_size().reshape(3, 1, 1, 1) * float(frame_rate))


@register_scene("plume", keys=("n_cameras", "width", "height", "frame", "seed", "phantom_resolution",
                               "noise", "peak", "rise", "swirl"))
def load(cfg) -> Scene:
    """Config keys: see the module doc."""
    n = read_int(cfg.get("n_cameras", 6), "config", "scene.n_cameras", 2)
    W, H = (read_int(cfg.get(k, d), "config", f"scene.{k}") for k, d in (("width", 160), ("height", 120)))
    frame = read_int(cfg.get("frame", 0), "config", "scene.frame", 0)
    seed = read_int(cfg.get("seed", 0), "config", "scene.seed", 0)
    phantom = read_int(cfg.get("phantom_resolution", 96), "config", "scene.phantom_resolution", 2)
    rise = read_float(cfg.get("rise", RISE), "config", "scene.rise", NONNEGATIVE)
    swirl = read_float(cfg.get("swirl", SWIRL), "config", "scene.swirl")
    cams = ring_cameras(n, W, H, focal=470.0 * H / 240.0)
    truth_grid = VoxelGrid.from_box(BOX_MIN, BOX_MAX, phantom)
    seconds = frame * SECONDS_PER_FRAME

    def render() -> dict[str, torch.Tensor]:
        truth = plume_density(truth_grid.centers(), seconds, seed, rise, swirl)[None]
        cropped, sub = _crop_to_support(truth * (truth > 1e-4), truth_grid)
        return {"truth": truth, "clean": render_image(cropped, sub, cams, step=0.5)}

    options = {"n_cameras": n, "width": W, "height": H, "frame": frame, "seed": seed, "phantom_resolution": phantom,
               "rise": rise, "swirl": swirl}
    found = cached("plume", options, render, [sys.modules[m] for m in _RENDER_CODE])
    truth, clean = found["truth"], found["clean"]
    peak = read_float(cfg.get("peak", 0.8), "config", "scene.peak", POSITIVE)
    scale = peak / float(clean.max().clamp_min(1e-12))
    clean, truth = clean * scale, truth * scale
    sigma = read_float(cfg.get("noise", 0.005), "config", "scene.noise", NONNEGATIVE)
    g = torch.Generator(device="cpu").manual_seed(seed + 1000 * frame + 11)
    images = (clean + sigma * torch.sqrt(1 + 4 * clean.clamp_min(0)) * torch.randn(clean.shape, generator=g)).clamp(0, 1)
    views = [f"cam{i:02d}" for i in range(n)]
    return Scene(
        name="plume", views=views, cameras=cams, images=images, bbox_min=BOX_MIN, bbox_max=BOX_MAX,
        default_holdout=[views[-1]], truth=truth, truth_grid=truth_grid,
        source=f"synthetic plume (seed {seed}, frame {frame})",
        meta={"frame": frame, "noise": sigma, "time": seconds, "velocity": {"rise": rise, "swirl": swirl}},
        up="+y", up_source="the synthetic plume's own (+y)", frame_rate=1.0 / SECONDS_PER_FRAME,
    )
