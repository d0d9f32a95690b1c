"""The built-in synthetic flame: seedable, flame-like, and free of the inverse crime (images
come from a finer phantom and finer steps than any reconstruction uses, plus sensor noise)."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from flamerecon.evaluate.metrics import resample_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.scenes import Scene, SceneError, load_scene

TINY = {"name": "synthetic", "n_cameras": 3, "width": 40, "height": 30, "phantom_resolution": 36}


@pytest.fixture(scope="module")
def tiny():
    return load_scene(dict(TINY))


def test_the_scene_has_named_views_images_in_range_and_a_default_holdout(small_scene):
    s = small_scene
    assert isinstance(s, Scene)
    assert s.views == [f"cam{i:02d}" for i in range(6)]
    assert s.default_holdout == ["cam05"]
    assert s.images.shape == (6, 3, 48, 64) and s.images.dtype == torch.float32
    assert s.images.min() >= 0 and s.images.max() <= 1
    assert s.images.max() > 0.5  # the flame is bright, not lost in the noise
    assert s.cameras.batch_size == 6
    assert s.image_size == (48, 64)


def test_the_truth_is_a_nonnegative_rgb_field_on_the_phantom_grid(small_scene):
    truth, grid = small_scene.truth, small_scene.truth_grid
    assert truth.shape == (3, *grid.shape)
    assert max(grid.resolution) == 48  # phantom_resolution cells along the longest side
    assert (grid.bbox_min, grid.bbox_max) == (small_scene.bbox_min, small_scene.bbox_max)
    assert truth.min() >= 0 and truth.max() > 0


def test_the_core_is_hot_and_the_edge_redder_and_fainter(small_scene):
    R, G, B = small_scene.truth
    total = small_scene.truth.sum(0)
    core = total > 0.5 * total.max()
    edge = (total > 0.02 * total.max()) & (total < 0.2 * total.max())
    assert core.sum() > 10 and edge.sum() > 10
    assert (R[core] >= G[core]).all() and (G[core] >= B[core]).all()
    green_over_red = G / R.clamp_min(1e-12)
    assert green_over_red[core].mean() > 1.5 * green_over_red[edge].mean()
    # the flame stands on y = 0 and is empty near the top of the box
    assert total[:, -2:, :].max() < 0.05 * total.max()


def test_same_seed_same_scene(tiny):
    again = load_scene(dict(TINY))
    assert torch.equal(again.images, tiny.images)
    assert torch.equal(again.truth, tiny.truth)


@pytest.mark.parametrize("change", [{"seed": 1}, {"frame": 3}])
def test_other_seeds_and_frames_give_other_flames(tiny, change):
    other = load_scene(dict(TINY, **change))
    assert (other.truth - tiny.truth).abs().mean() > 0.05 * tiny.truth.mean()
    assert (other.images - tiny.images).abs().mean() > 0.05 * tiny.images.mean()


def test_images_are_renders_of_the_stored_truth_plus_sensor_noise(tiny):
    clean_scene = load_scene(dict(TINY, noise=0.0))
    clean = render_image(clean_scene.truth, clean_scene.truth_grid, clean_scene.cameras, step=0.5)
    assert (clean - clean_scene.images).abs().max() < 5e-3  # same scale as the stored truth
    # noise: std = noise * sqrt(1 + 4 I), noise = 0.01 by default
    bright = (clean_scene.images > 0.1) & (clean_scene.images < 0.8)  # unclipped pixels
    z = ((tiny.images - clean_scene.images) / torch.sqrt(1 + 4 * clean_scene.images))[bright]
    assert bright.sum() > 200
    assert z.std().item() == pytest.approx(0.01, rel=0.2)
    assert abs(z.mean().item()) < 0.003


def test_no_inverse_crime_the_reconstruction_grid_cannot_reproduce_the_images(tiny):
    coarse = VoxelGrid.from_box(tiny.bbox_min, tiny.bbox_max, 12)
    rendered = render_image(resample_to(tiny.truth, coarse.shape), coarse, tiny.cameras, step=0.5)
    assert (rendered - tiny.images).abs().max() > 0.05


def test_the_default_phantom_is_finer_than_the_default_reconstruction_grid(repo_root):
    train = OmegaConf.load(repo_root / "conf" / "train.yaml")
    scene = OmegaConf.load(repo_root / "conf" / "scene" / "synthetic.yaml")
    assert scene.phantom_resolution >= 2 * train.grid.resolution
    assert scene.noise > 0
    assert (scene.n_cameras, scene.width, scene.height) == (8, 320, 240)


# The harder flame of conf/scene/synthetic_flame.yaml: a smooth field, uneven cameras and cameras
# given to the solver with a calibration error (the images stay the true cameras' renders).

def _centres(cams):
    E = cams.extrinsics.double()
    return -(E[:, :3, :3].transpose(1, 2) @ E[:, :3, 3:]).squeeze(-1)  # C = -R^T t


def _project(cams, point):
    """Pixel coordinates (B, 2) of one world point in every camera."""
    E, K = cams.extrinsics.double(), cams.intrinsics[:, :3, :3].double()
    p = (E[:, :3, :3] @ torch.tensor(point, dtype=torch.float64) + E[:, :3, 3]).unsqueeze(-1)
    q = (K @ p).squeeze(-1)
    return q[:, :2] / q[:, 2:]


def test_azimuths_place_the_cameras_unevenly():
    angles = [0.0, 30.0, 100.0, 250.0]
    scene = load_scene(dict(TINY, n_cameras=4, azimuths=angles))
    c = _centres(scene.cameras)
    found = torch.rad2deg(torch.atan2(c[:, 0], c[:, 2])) % 360
    assert found.tolist() == pytest.approx(angles, abs=1e-3)
    with pytest.raises(SceneError, match=r"^config: scene\.azimuths: got \[0\.0, 30\.0\]; it must be a list of "
                                         r"scene\.n_cameras = 4 angles"):
        load_scene(dict(TINY, n_cameras=4, azimuths=[0, 30]))


def test_a_calibration_error_moves_the_given_cameras_not_the_images(tiny):
    off = load_scene(dict(TINY, calibration_error=3.0))
    assert torch.equal(off.images, tiny.images)  # rendered by the true cameras
    assert torch.allclose(_centres(off.cameras), _centres(tiny.cameras), atol=1e-5)  # turned about its centre
    shift = (_project(off.cameras, (0.0, 0.62, 0.0)) - _project(tiny.cameras, (0.0, 0.62, 0.0))).norm(dim=-1)
    assert shift.tolist() == pytest.approx([3.0] * 3, abs=0.3)  # the principal point's ray: the tilt alone
    again = load_scene(dict(TINY, calibration_error=3.0, frame=2))
    assert torch.allclose(again.cameras.extrinsics, off.cameras.extrinsics)  # the rig's error: every frame
    other = load_scene(dict(TINY, calibration_error=3.0, seed=1))
    assert not torch.allclose(other.cameras.extrinsics, off.cameras.extrinsics)
    half = load_scene(dict(TINY, calibration_error=3.0, downscale=2))  # native pixels: half at half size
    shift = (_project(half.cameras, (0.0, 0.62, 0.0)) - _project(tiny.cameras, (0.0, 0.62, 0.0)) / 2).norm(dim=-1)
    assert shift.tolist() == pytest.approx([1.5] * 3, abs=0.3)


def test_the_smooth_field_is_a_smooth_hot_flame(tiny):
    smooth = load_scene(dict(TINY, field="smooth"))
    assert "smooth flame" in smooth.source and smooth.meta["field"] == "smooth"
    truth = smooth.truth
    assert truth.min() >= 0 and truth.max() > 0
    R, G, B = truth
    core = truth.sum(0) > 0.5 * truth.sum(0).max()
    assert core.sum() > 10 and (R[core] >= G[core]).all() and (G[core] >= B[core]).all()

    def roughness(v):  # what a 3-cell box blur removes, relative
        return float((v - torch.nn.functional.avg_pool3d(v[None], 3, stride=1, padding=1)[0]).norm() / v.norm())

    assert roughness(truth) < 0.6 * roughness(tiny.truth)  # measured 0.10 against 0.20
    with pytest.raises(SceneError, match=r"^config: scene\.field: got 'candle'; it must be one of "):
        load_scene(dict(TINY, field="candle"))


def test_the_flame_preset_is_seven_uneven_miscalibrated_views_of_a_smooth_flame(repo_root):
    node = OmegaConf.load(repo_root / "conf" / "scene" / "synthetic_flame.yaml")
    assert (node.name, node.n_cameras, node.field) == ("synthetic", 7, "smooth")
    gaps = sorted(b - a for a, b in zip(node.azimuths, [*node.azimuths[1:], node.azimuths[0] + 360]))
    assert len(node.azimuths) == 7 and gaps[-1] > 2 * gaps[0]  # unevenly spaced
    assert node.calibration_error >= 2 and node.noise > 0.01
    default = OmegaConf.load(repo_root / "conf" / "scene" / "synthetic.yaml")
    assert (default.field, default.azimuths, default.calibration_error) == ("turbulent", None, 0.0)
