"""Held-out scores beyond the full frame at the working resolution: PSNR inside the silhouette
union of the captured and the rendered view, and PSNR/SSIM at the capture's native resolution
(the scene loaded again with ``scene.downscale=1``, rendered only where the density can reach).
"""

from __future__ import annotations

import copy

import torch
from omegaconf import DictConfig, OmegaConf

from .cameras import camera_subset, cameras_to
from .grid import VoxelGrid
from .metrics import psnr, ssim
from .projector import camera_rays, integrate_dense, ray_box, support_box
from .scenes import Scene, load_scene
from .scenes.calibration import downscale_factor
from .silhouettes import silhouettes


def silhouette_union(rendered: torch.Tensor, scene: Scene, views: list[int],
                     options: dict) -> torch.Tensor:
    """(V, H, W) bool: where the captured view or the rendering shows flame, both by the
    silhouette ``options`` (the run's ``silhouette:`` node); the scene's own masks, when it
    has them, stand for the captured silhouettes."""
    if scene.masks is not None:
        captured = scene.masks[views].cpu()
    else:
        captured = silhouettes(scene.images[views], **options).cpu()
    return captured | silhouettes(rendered.clamp(0, 1), **options).cpu()


def masked_scores(rendered: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """PSNR of rendered (C, H, W) against captured inside ``mask`` (H, W) bool, and of a black
    image there: ``psnr_silhouette`` and ``psnr_black_silhouette``."""
    r, c = rendered[:, mask], captured[:, mask]  # (C, P)
    return {"psnr_silhouette": psnr(r, c), "psnr_black_silhouette": psnr(torch.zeros_like(c), c)}


def render_support(volume: torch.Tensor, grid: VoxelGrid, cams, step: float) -> torch.Tensor:
    """Render every pixel of every camera like :func:`~flamerecon.projector.render_image`, one
    camera at a time and marching only rays that cross the box of the nonzero density, so
    that full-resolution frames fit in memory: volume (C, nz, ny, nx) -> (B, C, H, W) on CPU."""
    C = volume.shape[0]
    support = volume.detach().abs().sum(0).reshape(-1).nonzero().squeeze(1)
    box = support_box(grid, support)
    H, W = int(cams.height[0]), int(cams.width[0])
    out = torch.zeros(cams.batch_size, C, H * W)
    for b in range(cams.batch_size):
        rays, _ = camera_rays(camera_subset(cams, [b]))
        near, far = ray_box(rays, *box)
        hit = (far > near).nonzero().squeeze(1)
        if hit.numel():
            with torch.no_grad():
                out[b][:, hit.cpu()] = integrate_dense(volume, grid, rays[hit], step, box).T.cpu()
    return out.reshape(cams.batch_size, C, H, W)


def native_scene(scene_cfg: DictConfig) -> Scene | None:
    """The scene at native resolution (``scene.downscale=1``), or None when the run already
    works at it (or its scene has no ``downscale``)."""
    if downscale_factor(scene_cfg) == 1:
        return None
    cfg = copy.deepcopy(scene_cfg) if isinstance(scene_cfg, DictConfig) else OmegaConf.create(dict(scene_cfg))
    cfg.downscale = 1
    return load_scene(cfg)


def native_scores(scene_cfg: DictConfig, volume: torch.Tensor, grid: VoxelGrid, names: list[str],
                  step: float) -> tuple[dict[str, dict[str, float]], tuple[int, int]] | None:
    """Per held-out view name: ``psnr_native``, ``ssim_native`` and ``psnr_black_native`` over
    the full native frame, and the native (width, height); None when there is nothing to add."""
    scene = native_scene(scene_cfg)
    if scene is None:
        return None
    views = [scene.views.index(n) for n in names]
    cams = cameras_to(camera_subset(scene.cameras, views), volume.device)
    rendered = render_support(volume, grid, cams, step)
    out = {}
    for img, v in zip(rendered, views):
        img, captured = scene.to_recorded(img), scene.recorded_view(v)
        out[scene.views[v]] = {
            "psnr_native": psnr(img, captured),
            "ssim_native": ssim(img, captured),
            "psnr_black_native": psnr(torch.zeros_like(captured), captured),
        }
    H, W = scene.image_size
    return out, (W, H)
