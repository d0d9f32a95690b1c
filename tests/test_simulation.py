"""The smoke simulator (:mod:`flamerecon.dynamics.simulation`) and its assimilation
(:mod:`flamerecon.dynamics.assimilation`): the projection leaves no divergence, advection moves
what it should and MacCormack keeps detail without new extrema, buoyancy lifts along the scene's
up axis, the source is re-injected, a density carried along a velocity history is read once,
and a simulation fitted through an identity "projector" finds the motion that made its data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.dynamics.assimilation import SimulationOptions, assimilate, simulation_box
from flamerecon.dynamics.simulation import (
    Smoke,
    advect_field,
    carry,
    central_divergence,
    inflow_region,
    project,
)
from flamerecon.errors import ArgumentError
from flamerecon.operators import CsrOperator
from flamerecon.operators.warp import advect_volume, warp_volume

SHAPE = (14, 18, 16)  # (nz, ny, nx)


def smooth_field(channels: int, seed: int = 0, shape=SHAPE) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(1, channels, *shape, generator=g, dtype=torch.float64)
    return torch.nn.functional.avg_pool3d(noise, 5, 1, 2)[0]


def blob(centre=(8.0, 6.0, 7.0), width: float = 2.0) -> torch.Tensor:
    z, y, x = torch.meshgrid(*[torch.arange(n, dtype=torch.float64) for n in SHAPE], indexing="ij")
    cx, cy, cz = centre
    return torch.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / (2 * width ** 2))[None]


def test_the_projection_leaves_no_central_divergence():
    u = smooth_field(3)
    assert central_divergence(u).abs().max() > 0.05
    projected = project(u, pad=6)
    assert central_divergence(projected).abs().max() < 1e-10
    # on the periodic box (no padding) it is a projection: twice is once, a gradient vanishes
    once = project(u, pad=0)
    assert torch.allclose(project(once, pad=0), once, atol=1e-10)
    phi = smooth_field(1, seed=1)[0]
    gradient = 0.5 * torch.stack([phi.roll(-1, d) - phi.roll(1, d) for d in (2, 1, 0)])  # periodic central
    assert project(gradient, pad=0).abs().max() < 1e-10 * gradient.abs().max() + 1e-12


def test_advection_moves_whole_cells_exactly_and_maccormack_keeps_detail_in_range():
    x = blob()
    shift = torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64).reshape(3, 1, 1, 1).expand(3, *SHAPE)
    moved = advect_field(x, shift)
    assert torch.allclose(moved[:, :, 2:, 1:], x[:, :, :-2, :-1], atol=1e-12)
    # a fractional shift three times: MacCormack is nearer the exact result and makes no new extremes
    frac = torch.tensor([0.4, 0.0, 0.0], dtype=torch.float64).reshape(3, 1, 1, 1).expand(3, *SHAPE)
    exact = blob((8.0 + 1.2, 6.0, 7.0))
    sl, mc = x, x
    for _ in range(3):
        sl, mc = advect_field(sl, frac), advect_field(mc, frac, "maccormack")
    assert (mc - exact).norm() < 0.7 * (sl - exact).norm()
    assert float(mc.min()) >= -1e-12 and float(mc.max()) <= float(x.max()) + 1e-12


@pytest.mark.parametrize(("up", "axis", "sign"), [("y", 1, 1.0), ("+x", 0, 1.0), ("-z", 2, -1.0)])
def test_buoyancy_lifts_the_smoke_along_the_scenes_up(up, axis, sign):
    smoke = Smoke(SHAPE, up, 0.5, 1.0, incompressible=False)
    x, u = blob(), torch.zeros(3, *SHAPE, dtype=torch.float64)
    for _ in range(3):
        x, u = smoke.step(x, u)
    inside = blob()[0] > 0.5
    assert float(u[axis][inside].mean()) * sign > 0.5  # three frames of about 0.5 cells/frame^2 at the core
    assert all(float(u[a][inside].abs().mean()) < 1e-9 for a in range(3) if a != axis)
    # incompressible: the same rise drives a return flow around it, and no divergence
    x, u = blob(), torch.zeros(3, *SHAPE, dtype=torch.float64)
    x, u = Smoke(SHAPE, up, 0.5, 1.0, pad=6).step(x, u)
    assert float(u[axis][inside].mean()) * sign > 0 and central_divergence(u).abs().max() < 1e-10


def test_the_source_is_re_injected_where_its_region_is():
    x = blob()
    region = inflow_region(x, "y", 0.5)
    heights = torch.arange(SHAPE[1], dtype=torch.float64) / (SHAPE[1] - 1)
    assert bool(region.any()) and not bool(region[:, heights >= 0.5, :].any())
    smoke = Smoke(SHAPE, "y", 0.0, 1.0, region, incompressible=False)
    up = torch.zeros(3, *SHAPE, dtype=torch.float64)
    up[1] = 1.0
    source = 2 * x * region
    after, _ = smoke.step(x, up, source)
    assert torch.allclose(after[:, region > 0], source[:, region > 0])
    assert torch.allclose(after[:, region == 0], advect_field(x, up)[:, region == 0])


def test_a_density_carried_along_a_history_is_read_once():
    x = blob()
    steady = 0.45 * torch.stack([torch.ones(SHAPE), torch.full(SHAPE, 0.5), torch.zeros(SHAPE)]).double()
    assert torch.allclose(carry(x, [steady] * 4), advect_volume(x, steady, 4), atol=1e-10)
    # two velocities in turn: the later one is traced first
    other = steady.flip(0)
    stepped = advect_volume(advect_volume(x, steady, 1), other, 1)  # one frame of each, interpolated twice
    once = carry(x, [steady, other])
    assert (once - stepped).abs().max() < 0.05 * float(x.max())
    # a source region fills the cells whose traces meet it with the smoke injected then
    region = torch.zeros(SHAPE, dtype=torch.float64)
    region[:, :3] = 1
    sources = [torch.full((1, *SHAPE), 7.0, dtype=torch.float64), torch.full((1, *SHAPE), 9.0, dtype=torch.float64)]
    up = torch.zeros(3, *SHAPE, dtype=torch.float64)
    up[1] = 1.0
    filled = carry(x, [up, up], region, sources)
    assert torch.allclose(filled[0, :, :3], torch.tensor(9.0, dtype=torch.float64))
    assert torch.allclose(filled[0, :, 3], torch.tensor(7.0, dtype=torch.float64))


@pytest.fixture(scope="module")
def tiny_setup():
    """A tiny plume frame's setup whose "projector" is the identity on every cell: its data are
    a density, so a fitted simulation can be checked against the motion that made them."""
    scene = fr.load_scene("plume", width=64, height=48, phantom_resolution=40)
    setup = fr.build(scene, fr.preset("plume", "grid.resolution=[16,18,14]"))
    m = int(np.prod(SHAPE))
    identity = CsrOperator.from_coo(torch.arange(m), torch.arange(m), torch.ones(m), (m, m))

    def with_data(density: torch.Tensor):
        return dataclasses.replace(setup, hull=torch.ones(SHAPE, dtype=torch.bool), voxel_index=torch.arange(m),
                                   operator=identity, pixels=density.float().reshape(1, -1).T.contiguous(),
                                   row_view=None, row_pixel=None)  # its rows are cells, not pixels

    return with_data


def test_a_simulation_fitted_to_a_window_finds_the_rise_that_made_it(tiny_setup):
    rise = torch.zeros(3, *SHAPE, dtype=torch.float64)
    rise[1] = 0.7
    frames = [blob((8.0, 5.0, 7.0))]
    for _ in range(3):
        frames.append(warp_volume(frames[-1], rise))
    options = SimulationOptions(window=3, control=4, smooth=1.0, iters=15, inflow=0.05, margin=3, pad=4,
                                incompressible=True, self_advection=True, fit_buoyancy=True, start="assimilated")
    found = assimilate(frames, [tiny_setup(f) for f in frames[1:]], options)
    assert sum(found.record["residual"]) < 0.1 * sum(found.record["residual_unmoved"])
    inside = frames[-1][0] > 0.3
    speed = found.velocity()[:, inside].mean(1)
    assert float(speed[1]) == pytest.approx(0.7, abs=0.15) and float(speed[[0, 2]].abs().max()) < 0.1
    ahead = list(found.predict(frames[-1].float(), 2))
    assert len(ahead) == 2 and ahead[1].shape == frames[-1].shape
    expected = warp_volume(warp_volume(frames[-1], rise), rise)
    assert (ahead[1].double() - expected).norm() < 0.35 * (frames[-1] - expected).norm()  # beats persistence


def test_the_simulated_box_spans_the_up_axis_and_the_smoke_across_it():
    x = blob((8.0, 6.0, 7.0), 1.0)
    box = simulation_box([x], "y", 2)
    assert (box[1].start, box[1].stop) == (0, SHAPE[1])
    assert box[2].start > 0 and box[2].stop < SHAPE[2] and box[0].start > 0


def test_simulation_options_are_checked():
    with pytest.raises(ArgumentError, match="simulation.window"):
        SimulationOptions(window=0)
    with pytest.raises(ArgumentError, match="simulation.scheme"):
        SimulationOptions(scheme="upwind")
    with pytest.raises(ArgumentError, match="simulation.iters: got 100000000"):
        SimulationOptions(iters=10**8)


def test_without_self_advection_or_projection_a_velocity_holds():
    u = smooth_field(3, seed=2)
    smoke = Smoke(SHAPE, "+y", 0.0, 1.0, incompressible=False, self_advection=False)
    x, held = smoke.step(blob(), u)
    assert torch.equal(held, u) and torch.allclose(x, advect_field(blob(), u))
    moved = Smoke(SHAPE, "+y", 0.0, 1.0, incompressible=False).step(blob(), u)[1]
    assert not torch.allclose(moved, u)  # its own advection moves it


def test_a_prediction_starts_from_the_velocity_given_or_its_own(tiny_setup):
    frames = [blob((8.0, 5.0, 7.0))]
    for _ in range(2):
        frames.append(warp_volume(frames[-1], torch.zeros(3, *SHAPE, dtype=torch.float64)))  # at rest
    given = torch.zeros(3, *SHAPE, dtype=torch.float64)
    given[0] = 1.0  # one cell per frame along x
    for start, moves in (("flow", True), ("assimilated", False)):
        options = SimulationOptions(window=2, control=4, iters=3, inflow=0.05, margin=3, pad=4, start=start,
                                    incompressible=False, fit_buoyancy=False)
        found = assimilate(frames, [tiny_setup(f) for f in frames[1:]], options)
        ahead = next(iter(found.predict(frames[-1].float(), 1, given)))
        shifted = advect_field(frames[-1], given)
        assert ((ahead.double() - shifted).norm() < 0.05 * shifted.norm()) == moves
