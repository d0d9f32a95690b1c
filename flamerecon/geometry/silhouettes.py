"""Silhouettes of the flame or smoke in each view, and the box their cones enclose.

A silhouette is where a view sees emission: the image (or its difference to a background
image) denoised, thresholded (Otsu or a fixed level), cleaned by a morphological opening and
closing, then dilated by a safety margin so that carving a visual hull never cuts real
emission. Thresholding runs in OpenCV on the CPU; masks return on the images' device.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.errors import ConfigError
from flamerecon.geometry.cameras import camera_centers, project_points
from flamerecon.geometry.grid import VoxelGrid

SILHOUETTE_METHODS = ("otsu", "threshold")


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of a float array (any shape), between its min and max."""
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return hi
    hist, edges = np.histogram(values, bins=bins, range=(lo, hi))
    p = hist.astype(np.float64) / hist.sum()
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * centres)
    total = m0[-1]
    w1 = 1.0 - w0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (total * w0 - m0) ** 2 / (w0 * w1)
    between[~np.isfinite(between)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _drop_specks(mask: np.ndarray, min_area: int) -> np.ndarray:
    """``mask`` (H, W) uint8 without its 8-connected blobs of fewer than ``min_area`` pixels."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False  # background
    return keep[labels].astype(mask.dtype)


def silhouette_signal(images: torch.Tensor, background: torch.Tensor | None = None,
                      blur_px: float = 0.0) -> np.ndarray:
    """What :func:`silhouettes` thresholds: per view (B, H, W) the brightest channel of the
    image (minus ``background``, clamped at 0), denoised by a Gaussian of ``blur_px``."""
    signal = images.detach().float()
    if background is not None:
        bg = background.detach().float().to(signal.device)
        if bg.dim() == 3:
            bg = bg[None]
        if bg.shape[-3:] != signal.shape[-3:] or bg.shape[0] not in (1, signal.shape[0]):
            raise ValueError(
                f"silhouette.background: shape {tuple(bg.shape)} does not match the images "
                f"{tuple(signal.shape)}"
            )
        signal = (signal - bg).clamp_min(0.0)
    signal = signal.amax(dim=1).cpu().numpy()
    if blur_px > 0:
        signal = np.stack([cv2.GaussianBlur(view, (0, 0), sigmaX=float(blur_px)) for view in signal])
    return signal


def silhouettes(
    images: torch.Tensor,
    method: str = "threshold",
    threshold: float | None = 0.03,
    dilate_px: int = 2,
    background: torch.Tensor | None = None,
    blur_px: float = 0.0,
    speck_px: int = 1,
    close_px: int = 0,
    field: str = "silhouette",
) -> torch.Tensor:
    """Binary silhouettes (B, H, W) bool of images (B, C, H, W) in [0, 1].

    - ``background``: (C, H, W) or (B, C, H, W) images without the flame; when given, the
      signal is what the flame adds to it (image minus background, clamped at 0), otherwise
      the image itself; the brightest channel counts;
    - ``method``: ``"threshold"`` uses the fixed ``threshold``; ``"otsu"`` picks each view's
      level from its denoised signal, never below ``threshold`` when one is given;
    - ``blur_px``: Gaussian denoising sigma in pixels before thresholding (0 = none);
    - ``speck_px``: connected blobs smaller than a (2 speck_px + 1)^2 square are noise and
      dropped (unlike an opening, this keeps thin tongue tips attached to the flame);
    - ``close_px``: radius of the closing that fills pinholes; ``dilate_px``: final safety
      margin in pixels.

    A pixel size larger than the images' larger side is a :class:`~flamerecon.errors.ConfigError`
    naming ``<field>.<option>`` (its kernel would not fit in memory and could change nothing).
    """
    if images.dim() != 4:
        raise ValueError(
            f"silhouettes: images must be (B, C, H, W), got shape {tuple(images.shape)}"
        )
    H, W = images.shape[-2:]
    for name, size in (("speck_px", speck_px), ("close_px", close_px), ("dilate_px", dilate_px),
                       ("blur_px", blur_px)):
        if size > max(H, W):
            raise ConfigError(f"{field}.{name}: got {size}; for {W}x{H} images it must be at most {max(H, W)} "
                              "px (a kernel wider than the image changes nothing more)")
    if method not in SILHOUETTE_METHODS:
        raise ValueError(f"silhouette.method: '{method}' is not one of {SILHOUETTE_METHODS}")
    if method == "threshold" and threshold is None:
        raise ValueError("silhouette.threshold: method 'threshold' needs a threshold in [0, 1]")
    signal = silhouette_signal(images, background, blur_px)
    masks = []
    for view in signal:
        if method == "otsu":
            level = otsu_threshold(view)
            if threshold is not None:
                level = max(level, float(threshold))
        else:
            level = float(threshold)
        mask = (view > level).astype(np.uint8)
        if speck_px > 0:
            mask = _drop_specks(mask, (2 * speck_px + 1) ** 2)
        if close_px > 0:
            mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disk(close_px))
        if dilate_px > 0:
            mask = cv2.dilate(mask, _disk(dilate_px))
        masks.append(torch.from_numpy(mask.astype(bool)))
    return torch.stack(masks).to(images.device)


def _axes_meeting_point(cams: PinholeCamera) -> torch.Tensor:
    """The point (3,) nearest (least squares) to every camera's optical axis."""
    centres = camera_centers(cams).double()
    axes = cams.extrinsics[:, 2, :3].double()  # camera z axis in world coordinates
    eye = torch.eye(3, dtype=torch.float64)
    P = eye - axes[:, :, None] * axes[:, None, :]
    return torch.linalg.lstsq(P.sum(0), (P @ centres[:, :, None]).sum(0)).solution.squeeze(-1)


def _carve(cams: PinholeCamera, masks: torch.Tensor, grid: VoxelGrid) -> torch.Tensor:
    """Which cells of ``grid`` (nz, ny, nx) bool may hold emission: each cell's centre lies
    within the cell's projected radius of the silhouette in every view."""
    centres = grid.centers().reshape(-1, 3)
    uv, depth = project_points(cams, centres)
    uv, depth = uv.double().numpy(), depth.double().numpy()
    half_diagonal = 0.5 * float(grid.voxel_size().norm())
    focal = cams.intrinsics[:, :2, :2].diagonal(dim1=1, dim2=2).amax(-1).double().numpy()
    keep = np.ones(centres.shape[0], dtype=bool)
    for b in range(cams.batch_size):
        outside = (~masks[b]).numpy().astype(np.uint8)
        distance = cv2.distanceTransform(outside, cv2.DIST_L2, 5)
        H, W = distance.shape
        u = np.floor(uv[b, :, 0])
        v = np.floor(uv[b, :, 1])
        inside = keep & (depth[b] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        radius = focal[b] * half_diagonal / np.maximum(depth[b][inside], 1e-9) + 1.0
        near = np.zeros_like(keep)
        near[inside] = distance[v[inside].astype(np.int64), u[inside].astype(np.int64)] <= radius
        keep &= near
    return torch.from_numpy(keep.reshape(grid.shape))


def estimate_bbox(
    cams: PinholeCamera,
    masks: torch.Tensor,
    resolution: int = 48,
    iterations: int = 4,
    margin: float = 0.05,
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Axis-aligned box around the intersection of the cameras' silhouette cones.

    ``masks`` (B, H, W) bool. Starts from a cube around the point nearest to every optical axis
    (half-side: the mean camera distance to it), carves it at ``resolution`` cells per side,
    shrinks the box to the surviving cells and repeats ``iterations`` times; the result is
    padded by ``margin`` of its size on each side. A point outside a view's image counts as
    outside that silhouette. Returns (bbox_min, bbox_max) in world units.
    """
    cams = PinholeCamera(
        cams.intrinsics.cpu(), cams.extrinsics.cpu(), cams.height.cpu(), cams.width.cpu()
    )
    masks = masks.cpu()
    if masks.dim() != 3 or masks.shape[0] != cams.batch_size:
        raise ValueError(f"estimate_bbox: masks must be (B, H, W) for {cams.batch_size} cameras")
    if not bool(masks.flatten(1).any(1).all()):
        empty = [b for b in range(cams.batch_size) if not bool(masks[b].any())]
        raise ValueError(f"estimate_bbox: the silhouettes of views {empty} are empty")
    centre = _axes_meeting_point(cams)
    half = float((camera_centers(cams).double() - centre).norm(dim=-1).mean())
    lo, hi = centre - half, centre + half
    for _ in range(iterations):
        grid = VoxelGrid.from_box(lo.tolist(), hi.tolist(), resolution)
        keep = _carve(cams, masks, grid)
        if not bool(keep.any()):
            raise ValueError(
                "estimate_bbox: the silhouette cones of the views do not intersect; "
                "check the calibration or set the box in the config (scene.bbox)"
            )
        k, j, i = torch.nonzero(keep, as_tuple=True)
        size = grid.voxel_size().double()
        idx_lo = torch.stack([i.min(), j.min(), k.min()]).double()
        idx_hi = torch.stack([i.max(), j.max(), k.max()]).double() + 1.0
        lo, hi = lo + (idx_lo - 1.0) * size, lo + (idx_hi + 1.0) * size
    pad = margin * (hi - lo)
    lo, hi = lo - pad, hi + pad
    return tuple(lo.tolist()), tuple(hi.tolist())  # type: ignore[return-value]
