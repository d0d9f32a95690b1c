"""VoxelGrid: resolution, index <-> world, cell centres, and agreement with grid_sample.

Voxel (k, j, i) of a (C, nz, ny, nx) array is the cell whose corner nearest bbox_min is
bbox_min + (i, j, k) * size; its value sits at the cell centre.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from flamerecon.geometry.grid import VoxelGrid, resolution_for_box


def test_an_int_resolution_counts_cells_along_the_longest_side_and_follows_the_aspect():
    grid = VoxelGrid.from_box((-0.5, 0.0, -0.5), (0.5, 1.5, 0.5), 24)
    assert grid.resolution == (16, 24, 16)
    assert grid.shape == (16, 24, 16)  # (nz, ny, nx)
    assert grid.num_voxels == 16 * 24 * 16
    assert resolution_for_box(10, (2.0, 1.0, 0.5)) == (10, 5, 2)
    # cells stay (nearly) cubic
    size = grid.voxel_size()
    assert torch.allclose(size, size.mean().expand(3), rtol=1e-6)


def test_an_explicit_triple_is_kept_and_bad_resolutions_are_refused():
    assert VoxelGrid.from_box((0, 0, 0), (1, 2, 3), [4, 5, 6]).resolution == (4, 5, 6)
    assert VoxelGrid.from_box((0, 0, 0), (1, 2, 3), [4, 5, 6]).shape == (6, 5, 4)
    with pytest.raises(ValueError, match="grid.resolution"):
        resolution_for_box(0, (1, 1, 1))
    with pytest.raises(ValueError, match="grid.resolution"):
        resolution_for_box([4, 5], (1, 1, 1))
    with pytest.raises(ValueError, match="empty"):
        VoxelGrid.from_box((0, 0, 0), (1, 0, 1), 8)


def test_index_to_world_and_back_is_the_identity(box_grid):
    g = torch.Generator().manual_seed(0)
    xyz = box_grid.lo() + torch.rand(100, 3, generator=g) * (box_grid.hi() - box_grid.lo())
    assert torch.allclose(box_grid.index_to_world(box_grid.world_to_index(xyz)), xyz, atol=1e-6)
    ijk = torch.rand(100, 3, generator=g) * torch.tensor(box_grid.resolution) - 0.5
    assert torch.allclose(box_grid.world_to_index(box_grid.index_to_world(ijk)), ijk, atol=1e-5)
    # the box faces sit half a cell outside the first and last centres
    assert torch.allclose(box_grid.world_to_index(box_grid.lo()), torch.full((3,), -0.5))
    res = torch.tensor(box_grid.resolution, dtype=torch.float32)
    assert torch.allclose(box_grid.world_to_index(box_grid.hi()), res - 0.5, atol=1e-5)


def test_cell_centres_start_half_a_cell_inside_bbox_min_with_x_fastest(box_grid):
    centres = box_grid.centers()
    assert centres.shape == (*box_grid.shape, 3)
    size = box_grid.voxel_size()
    assert torch.allclose(size, torch.full((3,), 0.125))
    assert torch.allclose(centres[0, 0, 0], box_grid.lo() + size / 2)
    # voxel (k, j, i) = (2, 5, 1) sits at bbox_min + ((i, j, k) + 0.5) * size
    assert torch.allclose(centres[2, 5, 1], box_grid.lo() + (torch.tensor([1.0, 5.0, 2.0]) + 0.5) * size)
    assert torch.allclose(centres[2, 5, 1], box_grid.index_to_world(torch.tensor([1.0, 5.0, 2.0])))
    assert torch.allclose(centres[-1, -1, -1], box_grid.hi() - size / 2, atol=1e-6)


def test_world_to_normalized_reads_each_voxel_at_its_centre_like_grid_sample(box_grid):
    g = torch.Generator().manual_seed(0)
    volume = torch.rand(2, *box_grid.shape, generator=g)
    coords = box_grid.world_to_normalized(box_grid.centers())  # (nz, ny, nx, 3) as x, y, z
    sampled = F.grid_sample(volume[None], coords[None], mode="bilinear", align_corners=False)[0]
    assert torch.allclose(sampled, volume, atol=1e-6)
    # halfway between two x-neighbours: their mean (trilinear interpolation)
    k, j, i = 3, 4, 2
    mid = 0.5 * (box_grid.centers()[k, j, i] + box_grid.centers()[k, j, i + 1])
    c = box_grid.world_to_normalized(mid).reshape(1, 1, 1, 1, 3)
    val = F.grid_sample(volume[None], c, mode="bilinear", align_corners=False).reshape(2)
    assert torch.allclose(val, 0.5 * (volume[:, k, j, i] + volume[:, k, j, i + 1]), atol=1e-6)
    # the box corners map to -1 and +1
    assert torch.allclose(box_grid.world_to_normalized(box_grid.lo()), -torch.ones(3))
    assert torch.allclose(box_grid.world_to_normalized(box_grid.hi()), torch.ones(3))


def test_scaled_keeps_the_box_and_multiplies_the_resolution(box_grid):
    fine = box_grid.scaled(2)
    assert fine.resolution == (16, 24, 12)
    assert (fine.bbox_min, fine.bbox_max) == (box_grid.bbox_min, box_grid.bbox_max)


def test_dense_scatters_hull_values_and_is_differentiable():
    grid = VoxelGrid.from_box((0, 0, 0), (1, 2, 3), [3, 4, 5])
    index = torch.tensor([0, 7, 59])
    values = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], requires_grad=True)
    vol = grid.dense(values, index)
    assert vol.shape == (2, 5, 4, 3)
    flat = vol.reshape(2, -1)
    assert torch.equal(flat[:, index].T, values.detach())
    assert float(flat.detach().sum()) == float(values.detach().sum())  # zero elsewhere
    (vol * torch.arange(vol.numel()).reshape(vol.shape)).sum().backward()
    assert torch.equal(values.grad, torch.stack([index, index + 60], 1).float())
