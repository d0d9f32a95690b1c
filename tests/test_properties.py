"""Property test: for random camera poses (inside or outside the box, axis-aligned or not) and
random small grids, the projector and the visual hull never crash and never return NaN/Inf."""

from __future__ import annotations

import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.geometry.hull import visual_hull
from flamerecon.operators import dottest
from flamerecon.operators.projector import MatrixFreeOperator, assemble, camera_rays, render_image

# whole numbers too, so that rays parallel to the box's faces (zero direction components) occur
coord = st.one_of(st.integers(-3, 3).map(float), st.floats(-4.0, 4.0, allow_nan=False))
point = st.tuples(coord, coord, coord)


@st.composite
def scenes(draw):
    lo = draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3))
    extent = draw(st.tuples(*[st.floats(0.1, 2.0)] * 3))
    res = draw(st.tuples(*[st.integers(1, 6)] * 3))
    grid = VoxelGrid(lo, tuple(a + e for a, e in zip(lo, extent)), res)
    n = draw(st.integers(1, 3))
    eyes = torch.tensor([draw(point) for _ in range(n)])
    targets = torch.tensor([draw(point) for _ in range(n)])
    up = torch.tensor(draw(st.sampled_from([(0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)])))
    forward = targets - eyes
    assume(bool((forward.norm(dim=1) > 1e-3).all()))
    assume(bool((torch.linalg.cross(forward, up.expand_as(forward)).norm(dim=1) > 1e-3 * forward.norm(dim=1)).all()))
    W, H = draw(st.integers(2, 10)), draw(st.integers(2, 10))
    f = draw(st.floats(2.0, 100.0))
    K = intrinsics_matrix(f, f, W / 2.0, H / 2.0).expand(n, 3, 3)
    cams = make_cameras(K, look_at(eyes, targets, tuple(up.tolist())), H, W)
    seed = draw(st.integers(0, 2**31 - 1))
    return grid, cams, seed


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenes())
def test_projector_and_hull_are_total_and_finite(case):
    grid, cams, seed = case
    g = torch.Generator().manual_seed(seed)
    H, W = int(cams.height[0]), int(cams.width[0])
    masks = torch.rand(cams.batch_size, H, W, generator=g) > 0.3

    hull = visual_hull(grid, cams, masks, margin_voxels=1)
    assert hull.shape == grid.shape and hull.dtype == torch.bool

    rays, flat = camera_rays(cams, masks)
    assert torch.isfinite(rays.origins).all() and torch.isfinite(rays.directions).all()
    assert flat.numel() == int(masks.sum())

    voxel_index = torch.arange(grid.num_voxels)  # every voxel, whatever the hull says
    x = torch.rand(grid.num_voxels, 2, generator=g)
    y = torch.rand(len(rays), 2, generator=g)
    for op in (assemble(grid, rays, voxel_index), MatrixFreeOperator(grid, rays, voxel_index)):
        ax, aty = op.forward(x), op.adjoint(y)
        assert ax.shape == (len(rays), 2) and aty.shape == (grid.num_voxels, 2)
        assert torch.isfinite(ax).all() and torch.isfinite(aty).all()
        assert (ax >= 0).all()  # nonnegative density, nonnegative weights
        dottest(op, x, y, rtol=1e-4, atol=1e-4)  # <A x, y> == <x, A^T y>

    image = render_image(x.T.reshape(2, *grid.shape).contiguous(), grid, cams)
    assert image.shape == (cams.batch_size, 2, H, W) and torch.isfinite(image).all()
