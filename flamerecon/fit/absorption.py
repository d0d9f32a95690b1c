"""Emission with absorption (the paper's eq. 1 with transparency < 1): each sample's emission
is dimmed by the density between it and the camera,

    p(ray) = integral rho_c(s) exp(-sigma * integral_0^s rho(u) du) ds,

``rho`` the channel mean of the density (the extinction is gray), ``sigma`` >= 0 a scalar in
1 / (density * world unit). sigma -> 0 gives the linear emission-only model of
:mod:`~flamerecon.operators.projector`; for a constant density it gives (1 - exp(-sigma rho L)) / sigma.

Quadrature on the projector's segments, exact for a density constant on each: segment k of
length l_k and extinction a_k = sigma rho_k l_k contributes
T_k rho_c,k l_k (1 - exp(-a_k)) / a_k, with T_k = exp(-sum_{j<k} a_j) (samples in ray order,
from the camera out). :func:`fit_absorption` fits (density, sigma) to the training pixels by
gradients through this renderer (Adam, density kept >= 0), starting from the linear solution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from flamerecon.evaluate.scores import score_views
from flamerecon.geometry.cameras import camera_subset, cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import HullGradient
from flamerecon.operators.projector import Rays, _chunks, camera_rays, ray_samples, support_box


def _escape_factor(a: torch.Tensor) -> torch.Tensor:
    """(1 - exp(-a)) / a, 1 at a = 0 (series below 1e-4, where the quotient loses digits)."""
    small = a < 1e-4
    safe = torch.where(small, torch.ones_like(a), a)
    return torch.where(small, 1.0 - 0.5 * a, -torch.expm1(-safe) / safe)


def integrate_absorbing(volume: torch.Tensor, grid: VoxelGrid, rays: Rays, sigma: torch.Tensor | float,
                        step: float = 0.5, box: tuple[torch.Tensor, torch.Tensor] | None = None
                        ) -> torch.Tensor:
    """Pixels (R, C) of a dense volume (C, nz, ny, nx) with absorption ``sigma`` (scalar, may be
    a tensor that requires grad) along ``rays`` (origins at the cameras); differentiable in
    both. ``box`` narrows the march as in :func:`~flamerecon.operators.projector.integrate_dense`."""
    C = volume.shape[0]
    sigma = torch.as_tensor(sigma, dtype=volume.dtype, device=volume.device)
    out = []
    for _, chunk in _chunks(rays, grid, step):
        points, length = ray_samples(chunk, grid, step, box)
        coords = grid.world_to_normalized(points)
        vals = F.grid_sample(volume[None], coords[None, None], mode="bilinear", padding_mode="zeros",
                             align_corners=False)[0, :, 0]  # (C, R, S)
        a = sigma * vals.mean(0) * length  # (R, S) extinction of each segment
        before = torch.cumsum(a, 1) - a  # optical depth from the camera to each segment's start
        weight = torch.exp(-before) * _escape_factor(a) * length
        out.append((vals * weight[None]).sum(-1).T)
    if not out:
        return volume.new_zeros(0, C)
    return torch.cat(out, 0)


@dataclass
class AbsorptionOptions:
    """Adam on (density, log sigma): ``iters`` steps, density step ``lr`` times the initial
    density's maximum, log-sigma step ``lr_sigma``; sigma starts where the brightest training
    ray's optical depth is ``start_depth`` (``fit_sigma=False``: sigma stays 0, the same refit
    of the linear model, a control); ``tv_eps`` smooths the TV penalty's kink (relative to the
    initial maximum)."""

    iters: int = 60
    lr: float = 0.002
    lr_sigma: float = 0.05
    start_depth: float = 0.1
    tv_eps: float = 1e-3
    fit_sigma: bool = True


@dataclass
class AbsorptionFit:
    """The fitted density (C, nz, ny, nx), sigma (and where it started), the loss per iteration."""

    volume: torch.Tensor
    sigma: float
    losses: list[float]
    sigma_start: float = 0.0


def training_rays(setup) -> Rays:
    """The silhouette rays of a pipeline ``Setup``'s training views (the rows of its operator)."""
    cams = cameras_to(camera_subset(setup.scene.cameras, setup.train), setup.pixels.device)
    rays, _ = camera_rays(cams, setup.masks[setup.train])
    return rays


def fit_absorption(setup, volume: torch.Tensor, l1: float = 0.0, tv: float = 0.0,
                   opts: AbsorptionOptions | None = None) -> AbsorptionFit:
    """Fit density and sigma of the absorbing model to the training pixels of ``setup`` (a
    pipeline Setup), from ``volume`` (C, nz, ny, nx; the linear solution) on its hull:
    minimise 0.5||R(x, sigma) - P||^2 + l1 sum(x) + tv * TV_eps(x), x >= 0."""
    opts = opts or AbsorptionOptions()
    grid, index = setup.grid, setup.voxel_index
    x0 = volume.to(setup.pixels).reshape(volume.shape[0], -1)[:, index].T.contiguous()
    rays = training_rays(setup)
    box = support_box(grid, index)
    peak = float(x0.max()) if float(x0.max()) > 0 else 1.0
    depth = float((setup.operator.forward(x0).mean(1)).max()) if x0.numel() else 0.0
    x = x0.clone().requires_grad_(True)
    sigma_start = opts.start_depth / max(depth, 1e-12)
    log_sigma = torch.tensor(math.log(sigma_start), dtype=x0.dtype,
                             device=x0.device, requires_grad=True)
    D = HullGradient(grid.shape, index) if tv > 0 else None
    eps = opts.tv_eps * peak
    groups = [{"params": [x], "lr": opts.lr * peak}]
    if opts.fit_sigma:
        groups.append({"params": [log_sigma], "lr": opts.lr_sigma})
    adam = torch.optim.Adam(groups)
    losses = []
    for _ in range(opts.iters):
        adam.zero_grad()
        sigma = log_sigma.exp() if opts.fit_sigma else 0.0
        pred = integrate_absorbing(grid.dense(x, index), grid, rays, sigma, setup.step, box)
        loss = 0.5 * (pred - setup.pixels).pow(2).sum() + l1 * x.sum()
        if D is not None:
            loss = loss + tv * (D.forward(x).pow(2).sum(0) + eps * eps).sqrt().sum()
        loss.backward()
        adam.step()
        with torch.no_grad():
            x.clamp_(min=0)
        losses.append(float(loss.detach()))
    sigma = float(log_sigma.detach().exp()) if opts.fit_sigma else 0.0
    return AbsorptionFit(grid.dense(x.detach(), index), sigma, losses,
                         sigma_start if opts.fit_sigma else 0.0)


def render_absorbing(volume: torch.Tensor, grid: VoxelGrid, cams, sigma: float, step: float = 0.5
                     ) -> torch.Tensor:
    """Every pixel of every camera with absorption: (C, nz, ny, nx) -> (B, C, H, W) on CPU."""
    B, H, W = cams.batch_size, int(cams.height[0]), int(cams.width[0])
    rays, _ = camera_rays(cameras_to(cams, volume.device))
    support = volume.abs().sum(0).reshape(-1).nonzero().squeeze(1)
    with torch.no_grad():
        pix = integrate_absorbing(volume, grid, rays, sigma, step, support_box(grid, support))
    return pix.T.reshape(volume.shape[0], B, H, W).transpose(0, 1).cpu()


def score_absorbing(setup, volume: torch.Tensor, sigma: float) -> tuple[dict[str, float], float]:
    """({held-out view: PSNR}, mean training PSNR) of the absorbing model's renders."""
    out = []
    for views in (setup.holdout, setup.train):
        imgs = render_absorbing(volume, setup.grid, camera_subset(setup.scene.cameras, views), sigma,
                                setup.step)
        out.append(score_views(imgs, setup.scene, views))
    return ({k: v["psnr"] for k, v in out[0].items()},
            float(np.mean([v["psnr"] for v in out[1].values()])))
