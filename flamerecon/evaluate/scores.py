"""How well a density predicts views: renders of a scene's cameras scored against what they
recorded (PSNR, SSIM, the all-black floor), inside the silhouette union of the captured and the
rendered view, and at the capture's native resolution (the scene loaded again with
``scene.downscale=1``, rendered only where the density can reach); ``renders/`` panels.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import torch

from flamerecon import interrupt
from flamerecon.evaluate.metrics import (
    DETAIL_REFERENCE_PX,
    DETAIL_SIGMA_PX,
    detail_correlation,
    psnr,
    psnr_aligned,
    resample_to,
    ssim,
    volume_errors,
)
from flamerecon.evaluate.result_warnings import BLACK_VIEW, is_black
from flamerecon.geometry.cameras import camera_subset, cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.photometry import apply_gain_offset
from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.operators.projector import render_image
from flamerecon.outputs.atomic import atomic_write_bytes, make_subfolder
from flamerecon.outputs.figures import heldout_figure
from flamerecon.outputs.names import file_stems
from flamerecon.scenes import Scene, load_scene
from flamerecon.scenes.calibration import downscale_factor


def captured_silhouettes(scene: Scene, views: list[int], options: dict) -> torch.Tensor:
    """(V, H, W) bool: where the captured views show flame, by the silhouette ``options`` (the
    run's ``silhouette:`` node); the scene's own masks, when it has them, stand for them."""
    if scene.masks is not None:
        return scene.masks[views].cpu()
    return silhouettes(scene.images[views], **options).cpu()


def silhouette_union(rendered: torch.Tensor, captured: torch.Tensor, options: dict) -> torch.Tensor:
    """(V, H, W) bool: where the captured view (``captured``, :func:`captured_silhouettes`) or
    the rendering (V, C, H, W) shows flame."""
    return captured | silhouettes(rendered.clamp(0, 1), **options).cpu()


def detail_sigma(scene: Scene) -> float:
    """The detail band's sigma in pixels of ``scene``'s images (..., H, W): 2 px per 270 pixels
    of the shorter side (:data:`~flamerecon.evaluate.metrics.DETAIL_SIGMA_PX` at ScalarFlow's 1/4
    resolution, 480 x 270; 4 px at 1/2; 1.78 px on the 320 x 240 synthetic flame), so that every
    resolution of a capture measures the same structures."""
    return DETAIL_SIGMA_PX * min(scene.images.shape[-2:]) / DETAIL_REFERENCE_PX


def masked_scores(rendered: torch.Tensor, captured: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """PSNR of rendered (C, H, W) against captured inside ``mask`` (H, W) bool, and of a black
    image there: ``psnr_silhouette`` and ``psnr_black_silhouette``."""
    r, c = rendered[:, mask], captured[:, mask]  # (C, P)
    return {"psnr_silhouette": psnr(r, c), "psnr_black_silhouette": psnr(torch.zeros_like(c), c)}


def render_support(volume: torch.Tensor, grid: VoxelGrid, cams, step: float) -> torch.Tensor:
    """:func:`~flamerecon.operators.projector.render_image` one camera at a time (each marching
    only the footprint of the nonzero density), so that full-resolution frames fit in memory:
    volume (C, nz, ny, nx) -> (B, C, H, W) on CPU."""
    return torch.cat([render_image(volume, grid, camera_subset(cams, [b]), step).cpu()
                      for b in range(cams.batch_size)])


def native_scene(scene_cfg: Mapping) -> Scene | None:
    """The scene at native resolution (``scene.downscale=1``), or None when the run already
    works at it (or its scene has no ``downscale``)."""
    if downscale_factor(scene_cfg) == 1:
        return None
    return load_scene({**scene_cfg, "downscale": 1})


def native_scores(scene_cfg: Mapping, volume: torch.Tensor, grid: VoxelGrid, names: list[str],
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
        if is_black(captured):
            undefined(out[scene.views[v]])
    H, W = scene.image_size
    return out, (W, H)


def render_scene_views(volume: torch.Tensor, grid: VoxelGrid, scene: Scene, views: list[int], step: float,
                       known: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Rendered images (len(views), C, H, W) of the density for the given view indices
    (none: an empty batch; ``known``: pixels already rendered, see
    :func:`~flamerecon.operators.projector.render_image`)."""
    if not views:
        return torch.zeros(0, volume.shape[0], *scene.image_size)
    cams = cameras_to(camera_subset(scene.cameras, views), volume.device)
    return render_image(volume, grid, cams, step, known).cpu()


def view_psnr(rendered: torch.Tensor, scene: Scene, view: int) -> float:
    """Full-frame PSNR of one render (C, H, W) against view ``view``, in recorded units: the
    ``psnr`` of :func:`score_views` alone (the monitor's; the full scores cost about a render)."""
    return psnr(scene.to_recorded(rendered), scene.recorded_view(view))


def score_views(rendered: torch.Tensor, scene: Scene, views: list[int],
                masks: torch.Tensor | None = None, captured_masks: torch.Tensor | None = None
                ) -> dict[str, dict[str, float]]:
    """Per view, in recorded units (:meth:`Scene.to_recorded`): full-frame PSNR and SSIM against
    the captured image, the PSNR of an all-black prediction (the floor that gives a number its
    meaning) and ``detail``, the full frame's detail correlation
    (:func:`~flamerecon.evaluate.metrics.detail_correlation`, sigma :func:`detail_sigma`); with
    ``masks`` (V, H, W) bool also both PSNRs inside them (see :func:`masked_scores`); with
    ``captured_masks`` (V, H, W) bool, the captured silhouettes, ``detail_silhouette``: the
    detail correlation inside them."""
    sigma = detail_sigma(scene)
    out = {}
    for k, (img, v) in enumerate(zip(rendered, views)):
        interrupt.check()
        img, captured = scene.to_recorded(img), scene.recorded_view(v)
        out[scene.views[v]] = {
            "psnr": psnr(img, captured),
            "ssim": ssim(img, captured),
            "psnr_black": psnr(torch.zeros_like(captured), captured),
            "psnr_aligned": psnr_aligned(img, captured),
            "detail": detail_correlation(img, captured, sigma),
        }
        if masks is not None:
            out[scene.views[v]].update(masked_scores(img, captured, masks[k]))
        if captured_masks is not None:
            out[scene.views[v]]["detail_silhouette"] = detail_correlation(img, captured, sigma, captured_masks[k])
        if is_black(captured):
            undefined(out[scene.views[v]])
    return out


def undefined(scores: dict) -> None:
    """A black view's scores: its PSNRs are undefined (NaN; null in metrics.json), with the
    reason beside them as ``psnr_undefined``."""
    scores.update({k: math.nan for k in scores if k.startswith("psnr")}, psnr_undefined=BLACK_VIEW)


def score_rendered(rendered: torch.Tensor, scene: Scene, views: list[int],
                   silhouette: dict | None = None) -> dict[str, dict[str, float]]:
    """:func:`score_views` of renders (V, C, H, W) of ``views``; with ``silhouette`` options
    also inside the silhouette union (PSNR) and the captured silhouettes (detail). No views:
    an empty table."""
    if not views:
        return {}
    if silhouette is None:
        return score_views(rendered, scene, views)
    captured = captured_silhouettes(scene, views, silhouette)
    return score_views(rendered, scene, views, silhouette_union(rendered, captured, silhouette), captured)


def write_renders(run_dir: Path, rendered: torch.Tensor, scene: Scene, views: list[int],
                  sigma: torch.Tensor | None = None) -> None:
    """renders/<view>.png: rendered | captured | |error| (| predicted sigma, with ``sigma``:
    the confidence images (V, C, H, W) of the renders) with titles and a colour bar
    (:func:`~flamerecon.outputs.figures.heldout_figure`), one per held-out view (the view
    name made a safe, unique file name, :func:`~flamerecon.outputs.names.file_stems`)."""
    folder = make_subfolder(run_dir, "renders")
    stems = file_stems(scene.views)
    for k, (img, v) in enumerate(zip(rendered, views)):
        captured = scene.recorded_view(v)
        spread = {} if sigma is None else {"sigma": sigma[k]}
        panel = heldout_figure(img, scene.images[v], scene.views[v], view_psnr(img, scene, v),
                               psnr(torch.zeros_like(captured), captured), **spread)
        ok, png = cv2.imencode(".png", np.ascontiguousarray(panel[..., ::-1]))
        if not ok:
            raise OSError(f"{folder}: could not encode the render of view {scene.views[v]}")
        atomic_write_bytes(folder / f"{stems[v]}.png", png.tobytes())


def score(scene: Scene, volume: torch.Tensor, grid: VoxelGrid, train: list[int], holdout: list[int],
          step: float, silhouette: dict | None = None,
          photometry: dict[str, tuple[float, float]] | None = None,
          train_pixels: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[dict, torch.Tensor]:
    """Metrics of a density (C, nz, ny, nx): held-out and training views (with ``silhouette``
    options also inside the silhouette union; training renders through each camera's
    ``photometry`` (gain, offset) when given), volume errors against the truth when the
    scene has one. ``train_pixels``: the training pixels the operator rendered
    (:meth:`~flamerecon.fit.build.Setup.training_pixels`), not marched again. Returns
    (metrics, held-out renders)."""
    held_imgs = render_scene_views(volume, grid, scene, holdout, step)
    train_imgs = render_scene_views(volume, grid, scene, train, step, train_pixels)
    if photometry:
        gain = torch.tensor([photometry[scene.views[v]][0] for v in train])
        offset = torch.tensor([photometry[scene.views[v]][1] for v in train])
        train_imgs = apply_gain_offset(train_imgs, gain, offset)
    metrics = {"heldout": score_rendered(held_imgs, scene, holdout, silhouette),
               "train": score_rendered(train_imgs, scene, train, silhouette)}
    if scene.truth is not None:
        truth = resample_to(scene.truth, grid.shape) if scene.truth_grid is not None and (
            scene.truth_grid.bbox_min == grid.bbox_min and scene.truth_grid.bbox_max == grid.bbox_max
        ) else None
        if truth is not None:
            metrics["volume"] = volume_errors(volume.cpu(), truth)
    return metrics, held_imgs
