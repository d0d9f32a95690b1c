"""The API's picture helpers: a camera that frames the flame for a novel view
(``fr.framing_camera``), a render or capture saved as a PNG (``fr.save_image``), and the scene's
camera count (``scene.num_views``; ``len(scene.cameras)`` is kornia's and raises)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.api import emission_box
from flamerecon.geometry.cameras import camera_centers, project_points


@pytest.fixture(scope="module")
def rec():
    scene = fr.load_scene("synthetic", width=48, height=36, n_cameras=5, phantom_resolution=32)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu",
                                       solver=fr.SolverOptions().with_values(max_iters=40))
    return fr.reconstruct(scene, options)


def test_the_scene_counts_its_cameras(rec):
    assert rec.scene.num_views == rec.scene.cameras.batch_size == len(rec.scene.views) == 5


def test_a_framing_camera_fills_its_image_with_the_flame_and_stands_upright(rec):
    width, height = 96, 64
    cams = fr.framing_camera(rec, [0, 120, 240], elevation_deg=20, width=width, height=height)
    near, far = emission_box(rec.density.numpy(), np.array(rec.grid.bbox_min), np.array(rec.grid.bbox_max))
    corners = torch.tensor([[(near, far)[(p >> a) & 1][a] for a in range(3)] for p in range(8)], dtype=torch.float32)
    uv, depth = project_points(cams, corners)
    assert bool((depth > 0).all())
    inside = (uv[..., 0] >= 0) & (uv[..., 0] <= width) & (uv[..., 1] >= 0) & (uv[..., 1] <= height)
    assert bool(inside.all()), "the flame's box leaves the image"
    border = torch.minimum(torch.minimum(uv[..., 0], width - uv[..., 0]), torch.minimum(uv[..., 1], height - uv[..., 1]))
    assert bool((border.amin(dim=1) < 0.1 * height).all()), "the flame does not fill the image"
    up = -rec.scene.cameras.extrinsics[:, 1, :3].mean(0)
    assert bool(((-cams.extrinsics[:, 1, :3]) @ (up / up.norm()) > 0.9).all())  # image up = the rig's up
    target = torch.from_numpy((near + far) / 2).float()
    first = camera_centers(rec.scene.cameras)[0] - target
    mine = camera_centers(cams)[0] - target
    flat = [v - (v @ up / up.norm()) * up / up.norm() for v in (first, mine)]
    assert float(torch.nn.functional.cosine_similarity(flat[0], flat[1], dim=0)) > 0.999  # azimuth 0: camera 0's side


def test_save_image_writes_what_it_was_given(tmp_path):
    rng = np.random.default_rng(0)
    colour = torch.from_numpy(rng.random((3, 6, 8)).astype(np.float32) * 1.2)  # some above 1: clipped
    path = fr.save_image(tmp_path / "sub" / "colour.png", colour)
    back = cv2.imread(str(path))[..., ::-1].transpose(2, 0, 1)
    np.testing.assert_array_equal(back, np.round(colour.clamp(0, 1).numpy() * 255).astype(np.uint8))
    grey = torch.linspace(0, 0.5, 48).reshape(1, 1, 6, 8)  # a batch of one grey image, scaled to its max
    back = cv2.imread(str(fr.save_image(tmp_path / "grey.png", grey, vmax=None)))
    assert (back[..., 0] == back[..., 2]).all() and back.max() == 255 and back.min() == 0


def test_a_render_saved_beside_its_capture_scores_as_fr_score_says(rec, tmp_path):
    """At vmax 1 the saved render and capture are in one scale: their PSNR from the PNGs is the
    held-out PSNR up to 8-bit rounding."""
    held = rec.setup.holdout[0]
    name = rec.scene.views[held]
    render = fr.render(rec.density, rec.grid, rec.scene.cameras)[held]
    mine = cv2.imread(str(fr.save_image(tmp_path / "render.png", render))).astype(float) / 255
    theirs = cv2.imread(str(fr.save_image(tmp_path / "capture.png", rec.scene.images[held]))).astype(float) / 255
    psnr = -10 * np.log10(np.mean((mine - theirs) ** 2))
    assert psnr == pytest.approx(fr.score(rec)["heldout"][name]["psnr"], abs=0.3)
