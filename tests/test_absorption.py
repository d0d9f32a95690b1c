"""The absorbing renderer against the analytic line integral, its limit sigma -> 0 (the linear
model), and a fit through it on the tiny scene."""

from __future__ import annotations

import math

import pytest
import torch

from flamerecon.fit.absorption import AbsorptionOptions, fit_absorption, integrate_absorbing
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import Rays, integrate_dense
from flamerecon.run.pipeline import prepare, solve
from tests.helpers import random_rays, tiny_cfg, tiny_synthetic


@pytest.mark.parametrize("sigma", [0.05, 0.7, 3.0])
def test_constant_box_matches_the_analytic_integral(sigma):
    grid = VoxelGrid.from_box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 8)
    rho = 1.5
    volume = torch.full((1, *grid.shape), rho, dtype=torch.float64)
    # rays along x (and back) through cell centres: the trilinear density integrates to rho * 1
    origins = torch.tensor([[-1.0, 0.5625, 0.4375], [2.0, 0.3125, 0.6875]], dtype=torch.float64)
    directions = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    got = integrate_absorbing(volume, grid, Rays(origins, directions), sigma, step=0.25)
    expected = (1.0 - math.exp(-sigma * rho * 1.0)) / sigma
    torch.testing.assert_close(got, torch.full_like(got, expected), rtol=1e-9, atol=1e-12)


def test_front_density_hides_the_back():
    """Order matters once emission and extinction differ: a channel that emits only behind a
    slab (extinction = channel mean) is dimmer seen through the slab than from the other side.
    (A gray emitter, emission = extinction, gives (1 - exp(-sigma int rho)) / sigma either way.)"""
    grid = VoxelGrid.from_box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (8, 1, 1))
    volume = torch.zeros(2, 1, 1, 8, dtype=torch.float64)
    volume[0, ..., :2] = 4.0  # a dense slab at small x in channel 0
    volume[1, ..., 6] = 1.0  # a lone emitter at large x in channel 1
    rays = Rays(torch.tensor([[-1.0, 0.5, 0.5], [2.0, 0.5, 0.5]], dtype=torch.float64),
                torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64))
    got = integrate_absorbing(volume, grid, rays, 1.0)
    linear = integrate_dense(volume, grid, rays)
    through, direct = float(got[0, 1]), float(got[1, 1])
    # the slab's extinction: mean over channels of 4.0 over two cells of 0.125 -> depth 0.5
    assert through == pytest.approx(direct * math.exp(-0.5), rel=1e-9)
    assert direct < float(linear[1, 1])  # the emitter dims itself a little too
    # the slab seen past the lone emitter (mean extinction 0.5 over one cell): dimmed by that
    assert float(got[1, 0]) == pytest.approx(float(got[0, 0]) * math.exp(-0.5 * 0.125), rel=1e-9)


def test_small_sigma_reduces_to_the_linear_model(box_grid):
    rays = random_rays(box_grid, 200)
    g = torch.Generator().manual_seed(0)
    volume = torch.rand(2, *box_grid.shape, generator=g)
    linear = integrate_dense(volume, box_grid, rays)
    assert linear.abs().max() > 0
    torch.testing.assert_close(integrate_absorbing(volume, box_grid, rays, 0.0), linear)
    for sigma in (1e-3, 1e-5):
        gap = (integrate_absorbing(volume, box_grid, rays, sigma) - linear).abs().max()
        assert gap <= 2 * sigma * float(linear.max()) ** 2  # first order in sigma


def test_sigma_gets_a_gradient(box_grid):
    rays = random_rays(box_grid, 50)
    volume = torch.rand(1, *box_grid.shape, generator=torch.Generator().manual_seed(1))
    sigma = torch.tensor(0.5, requires_grad=True)
    integrate_absorbing(volume, box_grid, rays, sigma).sum().backward()
    assert float(sigma.grad) < 0  # more absorption, darker pixels


def test_fit_from_the_linear_solution_lowers_the_loss():
    cfg = tiny_cfg("solver=tv", "solver.max_iters=30", "device=cpu")
    setup = prepare(cfg, tiny_synthetic(), torch.device("cpu"))
    result, l1, _ = solve(cfg, setup)
    fit = fit_absorption(setup, setup.volume(result.x), l1=l1, opts=AbsorptionOptions(iters=15))
    assert fit.losses[-1] < fit.losses[0]
    assert fit.sigma > 0 and math.isfinite(fit.sigma)
    assert float(fit.volume.min()) >= 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device")
def test_absorbing_renderer_on_cuda_matches_cpu(box_grid):
    rays = random_rays(box_grid, 100)
    volume = torch.rand(2, *box_grid.shape, generator=torch.Generator().manual_seed(2))
    cpu = integrate_absorbing(volume, box_grid, rays, 0.8)
    gpu = integrate_absorbing(volume.cuda(), box_grid, rays.to("cuda"), 0.8)
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-5, rtol=1e-5)
