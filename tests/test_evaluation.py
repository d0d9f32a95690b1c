"""Held-out evaluation beyond the full working frame: PSNR inside the silhouette union (against
hand-computed values), chunked rendering of only the rays that reach the density, native
resolution through ``scene.downscale`` end to end, and the real capture's native frame."""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf

from flamerecon.evaluate.scores import (
    captured_silhouettes,
    masked_scores,
    native_scene,
    render_support,
    silhouette_union,
)
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.run.pipeline import evaluate, reconstruct, summary_table
from flamerecon.scenes import load_scene
from tests.helpers import tiny_config

NATIVE = ["psnr_native", "ssim_native", "psnr_black_native"]


def test_masked_psnr_counts_only_the_pixels_inside_the_mask():
    captured = torch.tensor([[[0.2, 0.4], [0.0, 0.6]]])  # (1, 2, 2)
    rendered = torch.tensor([[[0.1, 0.4], [0.5, 0.3]]])
    mask = torch.tensor([[True, True], [False, True]])  # the 0.5 error at (1, 0) is outside
    scores = masked_scores(rendered, captured, mask)
    mse = (0.1**2 + 0.0 + 0.3**2) / 3
    assert scores["psnr_silhouette"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-4)
    black = (0.2**2 + 0.4**2 + 0.6**2) / 3
    assert scores["psnr_black_silhouette"] == pytest.approx(10 * math.log10(1 / black), abs=1e-4)


def test_the_silhouette_union_adds_what_the_rendering_shows_beyond_the_capture(small_scene):
    views = [0, 1]
    options = {"method": "threshold", "threshold": 0.05, "dilate_px": 0, "speck_px": 0}
    empty = torch.zeros_like(small_scene.images[views])
    captured = captured_silhouettes(small_scene, views, options)
    captured_only = silhouette_union(empty, captured, options)
    assert captured_only.any() and not captured_only.all()
    stray = empty.clone()
    stray[:, :, 0, 0] = 0.5  # a bright corner pixel in the rendering, dark in the capture
    union = silhouette_union(stray, captured, options)
    assert union[:, 0, 0].all() and not captured_only[:, 0, 0].any()
    assert int(union.sum()) == int(captured_only.sum()) + 2


def test_render_support_matches_the_full_render(small_scene):
    grid = VoxelGrid.from_box(small_scene.bbox_min, small_scene.bbox_max, 12)
    volume = torch.zeros(3, *grid.shape)
    volume[:, 3:7, 4:9, 5:8] = torch.rand(3, 4, 5, 3, generator=torch.Generator().manual_seed(1))
    cams = cameras_to(small_scene.cameras, "cpu")
    full = render_image(volume, grid, cams, 0.5)
    cropped = render_support(volume, grid, cams, 0.5)
    assert cropped.shape == full.shape and full.max() > 0.1
    assert torch.equal(cropped, full)


def test_a_synthetic_scene_downscaled_by_two_averages_the_native_pixels():
    cfg = {"name": "synthetic", "n_cameras": 3, "width": 32, "height": 24, "phantom_resolution": 24}
    native = load_scene(dict(cfg))
    half = load_scene({**cfg, "downscale": 2})
    assert half.images.shape == (3, 3, 12, 16)
    pooled = torch.nn.functional.avg_pool2d(native.images, 2)
    assert torch.allclose(half.images, pooled, atol=1e-6)
    assert torch.allclose(half.cameras.intrinsics[:, :2, :3], native.cameras.intrinsics[:, :2, :3] / 2)
    assert native_scene(OmegaConf.create({**cfg, "downscale": 2})).image_size == (24, 32)
    assert native_scene(OmegaConf.create(cfg)) is None


@pytest.fixture(scope="module")
def half_run(tmp_path_factory):
    """A tiny synthetic run at half its native 48x36, with its config saved like Hydra does."""
    run_dir = tmp_path_factory.mktemp("half")
    cfg = tiny_config("scene.downscale=2", "log.eval_every=0")
    reconstruct(cfg, run_dir)
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    return run_dir


def test_training_writes_the_silhouette_scores_but_not_the_native_ones(half_run):
    metrics = json.loads((half_run / "metrics.json").read_text())
    assert metrics["resolution"] == {"working": [24, 18]}
    held = metrics["heldout"]["cam04"]
    assert held["psnr_silhouette"] > held["psnr_black_silhouette"] + 5
    # inside the silhouettes the easy black background is gone: both numbers drop
    assert held["psnr_silhouette"] < held["psnr"] and held["psnr_black_silhouette"] < held["psnr_black"]
    assert not set(NATIVE) & set(held)


@pytest.mark.slow
def test_evaluate_scores_the_heldout_view_at_native_resolution(half_run):
    metrics = evaluate(half_run, device="cpu")
    assert metrics["resolution"] == {"working": [24, 18], "native": [48, 36]}
    held = metrics["heldout"]["cam04"]
    assert held["psnr_native"] > held["psnr_black_native"] + 5 and 0 < held["ssim_native"] <= 1
    # the native frame holds detail a 24x18 fit cannot render
    assert held["psnr_native"] < held["psnr"]
    # its black floor is the black floor of the native image
    native = load_scene({**OmegaConf.to_container(tiny_config().scene), "downscale": 1})
    mse = float((native.images[4].double() ** 2).mean())
    assert held["psnr_black_native"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-6)
    assert json.loads((half_run / "metrics.json").read_text())["heldout"]["cam04"] == pytest.approx(held)
    table = summary_table(metrics)
    assert "native 48x36 PSNR" in table and "inside silhouettes" in table
    assert "native" not in summary_table(evaluate(half_run, device="cpu", native=False))
