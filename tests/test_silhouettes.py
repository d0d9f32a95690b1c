"""Silhouettes (Otsu, fixed threshold, background subtraction, clean-up, margin), the box
around the silhouette cones, and what an empty one is blamed on."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from flamerecon.errors import HullError
from flamerecon.fit.checks import check_silhouettes
from flamerecon.fit.options import SilhouetteOptions
from flamerecon.geometry.cameras import make_cameras, project_points
from flamerecon.geometry.photometry import linearize
from flamerecon.geometry.silhouettes import estimate_bbox, otsu_threshold, silhouettes
from tests.helpers import tiny_synthetic
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


# ---------------------------------------------------------------------------------------------
# an empty silhouette is blamed on the setting that emptied it, with a value that gives one

def _specks(scene, size: int):
    """View 2 replaced by squares of ``size`` x ``size`` pixels at 0.8, far apart."""
    image = torch.zeros_like(scene.images[2])
    for y, x in ((5, 5), (20, 30), (28, 10)):
        image[:, y:y + size, x:x + size] = 0.8
    return {"images": torch.cat([scene.images[:2], image[None], scene.images[3:]])}


def _black_level(scene, level: float = 0.9):
    """Every view recorded as 0.1 + 0.5 x its image, linearized with ``scene.black_level``."""
    recorded = 0.1 + 0.5 * scene.images
    return {"recorded_images": recorded, "images": linearize(recorded, 1.0, level),
            "response": {"gamma": 1.0, "black_level": level}}


def _dark_view(scene):
    return {"images": torch.cat([scene.images[:2], torch.zeros_like(scene.images[2:3]), scene.images[3:]])}


EMPTY = {  # case: (scene change, silhouette options, the message after the scene's name)
    "threshold above every pixel": (lambda s: {}, {"threshold": 1.5},
                                    (r"every training view's silhouette is empty: silhouette.threshold=1.5 is above "
                                    r"every pixel of view 'cam00' \(brightest pixel 0\.\d+\); try "
                                    r"silhouette.threshold=0\.\d+$")),
    "otsu's level above every pixel": (lambda s: {}, {"method": "otsu", "threshold": 1.5},
                                       (r"the level silhouette.method=otsu chose .*try silhouette.threshold=0\.\d+ "
                                       r"and silhouette.method=threshold")),
    "single pixels dropped as specks": (lambda s: _specks(s, 1), {},
                                        (r"\['cam02'\] is empty.*silhouette.speck_px=1 drops every blob of view "
                                        r"'cam02' .* \(blobs smaller than 3x3 pixels\); try silhouette.speck_px=0 "
                                        r"or hold those views out")),
    "4x4 blobs dropped by speck_px=3": (lambda s: _specks(s, 4), {"speck_px": 3},
                                        r"silhouette.speck_px=3 drops every blob .*7x7.*; try silhouette.speck_px=1 "),
    "black level above every pixel": (_black_level, {},
                                      (r"scene.black_level=0.9 leaves no pixel of view 'cam00' above the threshold "
                                      r"\(brightest recorded value 0\.\d+\); try scene.black_level=0.45$")),
    "a black image file": (_dark_view, {}, (r"\['cam02'\] is empty.*: view 'cam02' is black; check its image file "
                                           r"or hold those views out \(holdout=\[...cam02\]\)$")),
}


@pytest.mark.parametrize("case", list(EMPTY))
def test_an_empty_silhouette_names_the_setting_that_emptied_it(case):
    change, options, message = EMPTY[case]
    scene = tiny_synthetic()
    scene = dataclasses.replace(scene, **change(scene))
    options = SilhouetteOptions(**options)
    masks = silhouettes(scene.images, **options.as_dict())
    with pytest.raises(HullError, match=message) as info:
        check_silhouettes(scene, masks, [0, 1, 2, 3], options)
    key, value = (re.search(r"try (\S+)=(\S+)", str(info.value)) or re.match("()()", "")).groups()
    if key.startswith("silhouette."):  # the value suggested gives the view a silhouette
        view = int(re.search(r"view '(cam\d+)'", str(info.value)).group(1)[3:])
        name = key.split(".")[1]
        fixed = dataclasses.replace(options, method="threshold",
                                    **{name: int(value) if name == "speck_px" else float(value)})
        assert silhouettes(scene.images[view:view + 1], **fixed.as_dict()).any()
