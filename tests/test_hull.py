"""The visual hull (paper section III-B): a voxel survives unless some training camera sees
its centre, in front of it and inside its image, on a pixel outside the silhouette."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy import ndimage

from flamerecon.evaluate.metrics import resample_to
from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import carve_counts, visual_hull
from flamerecon.geometry.silhouettes import silhouettes

W = H = 16
GRID = VoxelGrid.from_box((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), 8)


def camera(eye, target, focal):
    K = intrinsics_matrix(focal, focal, W / 2, H / 2)
    return make_cameras(K, look_at([eye], [target]), H, W)


def pixel_of_each_voxel(cams, grid: VoxelGrid):
    """Independent pinhole projection of every voxel centre: pixel (u, v) (integer, pixel
    (u, v) covers [u, u+1) x [v, v+1)) and depth, each (nz, ny, nx), for the first camera."""
    E = cams.extrinsics[0].double().numpy()
    K = cams.intrinsics[0, :3, :3].double().numpy()
    X = grid.centers().double().numpy().reshape(-1, 3)
    cam = X @ E[:3, :3].T + E[:3, 3]
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = cam @ K.T
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    u = np.floor(np.nan_to_num(u, nan=-1, posinf=-1, neginf=-1)).astype(np.int64)
    v = np.floor(np.nan_to_num(v, nan=-1, posinf=-1, neginf=-1)).astype(np.int64)
    return [torch.from_numpy(a.reshape(grid.shape)) for a in (u, v, depth)]


def seen_by(cams, grid):
    u, v, depth = pixel_of_each_voxel(cams, grid)
    return (depth > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H), u, v


def test_an_empty_silhouette_carves_exactly_the_voxels_the_camera_sees():
    # a narrow camera: the grid's corners near it fall outside its image
    cams = camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), focal=60.0)
    seen, _, _ = seen_by(cams, GRID)
    assert seen.any() and (~seen).any()
    empty = torch.zeros(1, H, W, dtype=torch.bool)
    assert torch.equal(carve_counts(GRID, cams, empty)[0], seen)
    assert torch.equal(visual_hull(GRID, cams, empty, margin_voxels=0), ~seen)


def test_voxels_behind_the_camera_are_kept():
    # a wide camera at the grid centre looking at +z: everything with z < 0 is behind it
    cams = camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), focal=2.0)
    hull = visual_hull(GRID, cams, torch.zeros(1, H, W, dtype=torch.bool), margin_voxels=0)
    z = GRID.centers()[..., 2]
    assert hull[z < 0].all()
    assert not hull[z > 0.2].any()


def test_a_full_silhouette_carves_nothing():
    cams = camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), focal=10.0)
    assert visual_hull(GRID, cams, torch.ones(1, H, W, dtype=torch.bool), margin_voxels=0).all()


def test_a_voxel_survives_iff_it_is_unseen_or_lands_inside_the_silhouette():
    cams = camera((0.4, 1.0, 2.5), (0.0, 0.0, 0.0), focal=12.0)
    vv, uu = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    disc = ((uu - 7.0) ** 2 + (vv - 9.0) ** 2 < 16.0)[None]
    seen, u, v = seen_by(cams, GRID)
    lands_inside = torch.zeros_like(seen)
    lands_inside[seen] = disc[0, v[seen], u[seen]]
    hull = visual_hull(GRID, cams, disc, margin_voxels=0)
    assert lands_inside.any() and (seen & ~lands_inside).any()
    assert torch.equal(hull, ~seen | lands_inside)


def test_every_camera_must_agree_and_the_margin_grows_the_hull_by_whole_voxels():
    K = intrinsics_matrix(12.0, 12.0, W / 2, H / 2).expand(2, 3, 3)
    E = look_at([[0.0, 0.0, 3.0], [3.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]] * 2)
    cams = make_cameras(K, E, H, W)
    masks = torch.zeros(2, H, W, dtype=torch.bool)
    masks[:, 5:11, 6:10] = True
    carved = carve_counts(GRID, cams, masks)
    hull0 = visual_hull(GRID, cams, masks, margin_voxels=0)
    assert torch.equal(hull0, ~carved[0] & ~carved[1])
    assert hull0.any() and (~hull0).any()
    hull1 = visual_hull(GRID, cams, masks, margin_voxels=1)
    grown = ndimage.binary_dilation(hull0.numpy(), structure=np.ones((3, 3, 3), bool))
    assert np.array_equal(hull1.numpy(), grown)


# --------------------------------------------------------------------------- synthetic flame


@pytest.fixture(scope="module")
def flame_hull(small_scene, repo_root):
    """The hull of the small synthetic scene on a 24-cell grid with the pipeline's default
    silhouette and hull settings (read from conf/train.yaml), and the phantom resampled to
    that grid."""
    cfg = OmegaConf.load(repo_root / "conf" / "train.yaml")
    grid = VoxelGrid.from_box(small_scene.bbox_min, small_scene.bbox_max, 24)
    masks = silhouettes(small_scene.images, **cfg.silhouette)
    hull = visual_hull(grid, small_scene.cameras, masks, int(cfg.hull.margin_voxels))
    assert small_scene.truth_grid.bbox_min == grid.bbox_min
    truth = resample_to(small_scene.truth, grid.shape).sum(0)
    return hull, truth


def test_the_flame_hull_keeps_its_emission_and_carves_most_of_the_box(flame_hull):
    hull, truth = flame_hull
    assert truth[hull].sum() >= 0.999 * truth.sum()
    assert truth[truth > 0.05 * truth.max()].numel() > 100
    assert hull[truth > 0.05 * truth.max()].all()
    assert hull.float().mean() < 0.5  # the hull is informative: most of the box is carved


def test_the_flame_hull_contains_the_phantom_support(flame_hull):
    hull, truth = flame_hull
    support = truth > 0.01 * truth.max()
    assert hull[support].all()
