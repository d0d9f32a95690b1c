"""Silhouettes (Otsu, fixed threshold, background subtraction, clean-up, margin) and the box
around the silhouette cones."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamerecon.geometry.cameras import make_cameras, project_points
from flamerecon.geometry.silhouettes import estimate_bbox, otsu_threshold, silhouettes
from tests.helpers.views import ring_cameras

H, W = 48, 64


def disc(cx=30.0, cy=22.0, r=10.0) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    return (x - cx) ** 2 + (y - cy) ** 2 < r**2


def noisy_scene(seed=0) -> tuple[torch.Tensor, torch.Tensor]:
    """Image (1, 1, H, W): a disc at 0.6 over dark noise plus one bright speck; and the disc."""
    g = torch.Generator().manual_seed(seed)
    truth = disc()
    image = 0.6 * truth.float() + 0.03 * torch.rand(H, W, generator=g)
    image[5, 55] = 0.9  # a single hot pixel
    return image[None, None], truth


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_otsu_threshold_splits_two_levels():
    values = np.concatenate([np.full(900, 0.1), np.full(100, 0.7)])
    assert 0.1 < otsu_threshold(values) <= 0.7


@pytest.mark.parametrize("method, threshold", [("otsu", None), ("otsu", 0.03), ("threshold", 0.3)])
def test_silhouette_finds_the_disc_and_drops_specks(method, threshold):
    image, truth = noisy_scene()
    mask = silhouettes(image, method=method, threshold=threshold, dilate_px=0)
    assert mask.shape == (1, H, W) and mask.dtype == torch.bool
    assert iou(mask[0], truth) > 0.9
    assert not bool(mask[0, 5, 55])  # the opening removed the hot pixel


def test_dilation_margin_contains_the_tight_mask():
    image, _ = noisy_scene()
    tight = silhouettes(image, method="otsu", dilate_px=0)
    wide = silhouettes(image, method="otsu", dilate_px=3)
    assert bool((tight <= wide).all())
    assert wide.sum() > tight.sum() * 1.3  # a 10 px disc grown by 3 px: about 1.69x the area


def test_background_subtraction():
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    background = (0.2 + 0.5 * x * y)[None].expand(3, H, W)  # bright, uneven, colour
    truth = disc(40, 25, 8)
    image = background + 0.25 * truth.float()
    mask = silhouettes(image[None], background=background, dilate_px=0, blur_px=0)
    assert iou(mask[0], truth) > 0.9
    plain = silhouettes(image[None], dilate_px=0, blur_px=0)  # without it the gradient leaks in
    assert iou(plain[0], truth) < 0.7


def test_bad_options():
    image, _ = noisy_scene()
    with pytest.raises(ValueError, match="silhouette.method"):
        silhouettes(image, method="magic")
    with pytest.raises(ValueError, match="silhouette.threshold"):
        silhouettes(image, method="threshold", threshold=None)
    with pytest.raises(ValueError, match="silhouette.background"):
        silhouettes(image, background=torch.zeros(1, 5, 5))


def test_estimated_box_hugs_a_sphere():
    """Eight ring cameras see a sphere; the box around the cones holds it and not much more."""
    w2c = ring_cameras(8)
    K = torch.tensor([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]]).expand(8, 3, 3)
    cams = make_cameras(K, w2c.float(), H, W)
    centre, radius = torch.tensor([0.15, -0.1, 0.2]), 0.35
    uv, depth = project_points(cams, centre[None])
    masks = torch.stack(
        [
            disc(float(uv[b, 0, 0]), float(uv[b, 0, 1]), 60.0 * radius / float(depth[b, 0]))
            for b in range(8)
        ]
    )
    lo, hi = estimate_bbox(cams, masks)
    lo, hi = torch.tensor(lo), torch.tensor(hi)
    assert bool((lo < centre - radius).all() and (hi > centre + radius).all())
    assert bool((lo > centre - 2 * radius).all() and (hi < centre + 2 * radius).all())


def test_estimate_box_errors():
    cams = make_cameras(torch.eye(3)[None].expand(2, 3, 3) * 50, ring_cameras(2).float(), H, W)
    masks = torch.zeros(2, H, W, dtype=torch.bool)
    masks[0, 10:20, 10:20] = True
    with pytest.raises(ValueError, match=r"silhouettes of views \[1\] are empty"):
        estimate_bbox(cams, masks)
