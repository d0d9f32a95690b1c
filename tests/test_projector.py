"""The emission-only projector against analytic line integrals, its adjoint, and its backends.

A pixel is the integral, in world units, of the trilinearly interpolated density along its
ray. The interpolant of a grid ramps linearly to zero over the half voxel outside the box
(``grid_sample`` with zero padding), so rays are marched through the box grown by half a
voxel; for a constant grid the two ramps add exactly the missing half voxels back.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from flamerecon.geometry.cameras import pixel_centers, pixel_rays
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators import CsrOperator
from flamerecon.operators.projector import (
    MatrixFreeOperator,
    Rays,
    assemble,
    camera_rays,
    cells_touching,
    footprint,
    integrate_dense,
    make_operator,
    march_box,
    packed_samples,
    ray_samples,
    render_image,
    support_box,
)
from tests.helpers import random_hull, random_rays, ring_of_cameras


def axis_rays(grid: VoxelGrid, axis: int, sign: float, transverse: torch.Tensor) -> Rays:
    """Rays along ``sign`` * world axis ``axis``, starting 1 unit outside the box, through the
    transverse world coordinates ``transverse`` (R, 2) of the other two axes."""
    others = [a for a in range(3) if a != axis]
    R = transverse.shape[0]
    origins = torch.zeros(R, 3)
    origins[:, others] = transverse
    origins[:, axis] = grid.bbox_min[axis] - 1.0 if sign > 0 else grid.bbox_max[axis] + 1.0
    directions = torch.zeros(R, 3)
    directions[:, axis] = sign
    return Rays(origins, directions)


def interior_points(grid: VoxelGrid, axis: int, n: int, seed: int = 0) -> torch.Tensor:
    """Random transverse coordinates (n, 2) at least half a voxel inside the box, where the
    interpolant of a constant grid is that constant."""
    others = [a for a in range(3) if a != axis]
    lo, hi, size = grid.lo()[others], grid.hi()[others], grid.voxel_size()[others]
    g = torch.Generator().manual_seed(seed)
    return lo + size / 2 + torch.rand(n, 2, generator=g) * (hi - lo - size)


def both_backends(grid, rays, voxel_index, step=0.5):
    return {
        "assembled": make_operator("assembled", grid, rays, voxel_index, step),
        "matrix_free": make_operator("matrix_free", grid, rays, voxel_index, step),
    }


# --------------------------------------------------------------------------- analytic integrals


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_constant_box_integrates_to_value_times_box_length(box_grid, axis, sign):
    c = 2.5
    volume = torch.full((1, *box_grid.shape), c)
    rays = axis_rays(box_grid, axis, sign, interior_points(box_grid, axis, 20))
    length = box_grid.bbox_max[axis] - box_grid.bbox_min[axis]  # 1.0, 1.5, 0.75
    expected = torch.full((20, 1), c * length)
    assert torch.allclose(integrate_dense(volume, box_grid, rays), expected, rtol=1e-5)
    everything = torch.arange(box_grid.num_voxels)
    x = torch.full((box_grid.num_voxels, 1), c)
    for name, op in both_backends(box_grid, rays, everything).items():
        assert torch.allclose(op.forward(x), expected, rtol=1e-5), name


def test_a_ray_along_a_box_face_sees_half_the_constant(box_grid):
    # on the face the transverse interpolant has ramped down to one half
    c = 2.0
    volume = torch.full((1, *box_grid.shape), c)
    z_mid = 0.5 * (box_grid.bbox_min[2] + box_grid.bbox_max[2]) + 0.01
    rays = axis_rays(box_grid, 0, 1.0, torch.tensor([[box_grid.bbox_min[1], z_mid]]))
    assert integrate_dense(volume, box_grid, rays).item() == pytest.approx(0.5 * c * 1.0, rel=1e-5)
    # and a ray half a voxel outside the face sees nothing
    outside = box_grid.bbox_min[1] - 0.5 * 0.125 - 1e-4
    rays = axis_rays(box_grid, 0, 1.0, torch.tensor([[outside, z_mid]]))
    assert integrate_dense(volume, box_grid, rays).item() == 0.0


def test_one_voxel_integrates_to_value_times_voxel_side_along_an_axis_through_its_centre(box_grid):
    volume = torch.zeros(1, *box_grid.shape)
    k, j, i = 2, 7, 3
    volume[0, k, j, i] = 4.0
    centre = box_grid.centers()[k, j, i]
    rays = axis_rays(box_grid, 2, 1.0, centre[None, :2])
    # the hat is a triangle of height 4 and half-width 0.125 along z
    assert integrate_dense(volume, box_grid, rays).item() == pytest.approx(4.0 * 0.125, rel=1e-5)


def gaussian_line_integral(origins, directions, mu, sigma):
    """Analytic integral of exp(-|p - mu|^2 / (2 sigma^2)) along full lines (R,)."""
    w = mu - origins
    perp2 = (w**2).sum(-1) - (w * directions).sum(-1) ** 2
    return torch.exp(-perp2 / (2 * sigma**2)) * sigma * math.sqrt(2 * math.pi)


def gaussian_case(n: int):
    """A Gaussian (sigma 0.15, 4 sigma to the box faces) sampled at the cell centres of an
    n^3 grid, and 200 oblique rays passing within about 1.2 sigma of its centre."""
    grid = VoxelGrid.from_box((-0.6, -0.6, -0.6), (0.6, 0.6, 0.6), n)
    sigma, mu = 0.15, torch.tensor([0.03, -0.02, 0.05])
    volume = torch.exp(-((grid.centers() - mu) ** 2).sum(-1) / (2 * sigma**2))[None]
    g = torch.Generator().manual_seed(0)
    d = F.normalize(torch.randn(200, 3, generator=g), dim=-1)
    through = mu + (torch.rand(200, 3, generator=g) - 0.5) * 0.3
    rays = Rays(through - 2.0 * d, d)
    numeric = integrate_dense(volume, grid, rays)[:, 0]
    return numeric, gaussian_line_integral(rays.origins, d, mu, sigma)


def test_gaussian_blob_matches_its_analytic_line_integral_and_converges():
    fine, exact = gaussian_case(40)
    assert ((fine - exact).abs() / exact).max() < 0.01
    # the error is the trilinear interpolation's: second order in the voxel size
    coarse, _ = gaussian_case(20)
    assert (coarse - exact).abs().max() > 3.0 * (fine - exact).abs().max()


# --------------------------------------------------------------------------- adjoint and backends


def test_assembled_and_matrix_free_agree_forward_and_adjoint(box_grid):
    rays = random_rays(box_grid, 300, seed=2)
    voxel_index = random_hull(box_grid, seed=3)
    ops = both_backends(box_grid, rays, voxel_index)
    assert isinstance(ops["assembled"], CsrOperator)
    assert isinstance(ops["matrix_free"], MatrixFreeOperator)
    g = torch.Generator().manual_seed(4)
    x = torch.rand(voxel_index.numel(), 3, generator=g)
    y = torch.randn(300, 3, generator=g)
    fa, fm = ops["assembled"].forward(x), ops["matrix_free"].forward(x)
    aa, am = ops["assembled"].adjoint(y), ops["matrix_free"].adjoint(y)
    assert (fa - fm).abs().max() <= 1e-5 * fa.abs().max()
    assert (aa - am).abs().max() <= 1e-5 * aa.abs().max()


def test_the_cells_touching_one_voxel_are_the_eight_around_it(box_grid):
    nx, ny, nz = box_grid.resolution
    i, j, k = 3, 0, 5  # on the grid's y = 0 face
    live = cells_touching(box_grid, torch.tensor([(k * ny + j) * nx + i]))
    assert live.shape == (nz + 1, ny + 1, nx + 1)
    # cell [k+1, j+1, i+1] has lower corner (i, j, k): the voxel is a corner of the cells with
    # lower corners i-1..i, j-1..j, k-1..k, i.e. entries i..i+1, j..j+1, k..k+1
    expected = torch.zeros_like(live)
    expected[k:k + 2, j:j + 2, i:i + 2] = True
    assert torch.equal(live, expected)


def test_column_m_of_the_operator_is_grid_voxel_voxel_index_m(box_grid):
    rays = random_rays(box_grid, 200, seed=5)
    voxel_index = random_hull(box_grid, seed=6)
    g = torch.Generator().manual_seed(7)
    x = torch.rand(voxel_index.numel(), 2, generator=g)
    volume = torch.zeros(2, box_grid.num_voxels)
    volume[:, voxel_index] = x.T
    volume = volume.reshape(2, *box_grid.shape)
    op = assemble(box_grid, rays, voxel_index)
    box = support_box(box_grid, voxel_index)
    direct = integrate_dense(volume, box_grid, rays, box=box)
    assert (op.forward(x) - direct).abs().max() <= 1e-5 * direct.abs().max()


def test_the_matrix_free_forward_is_differentiable(box_grid):
    rays = random_rays(box_grid, 50)
    op = MatrixFreeOperator(box_grid, rays, random_hull(box_grid))
    x = torch.rand(op.shape[1], 1, requires_grad=True)
    op.forward(x).sum().backward()
    ones = torch.ones(op.shape[0], 1)
    assert torch.allclose(x.grad, op.adjoint(ones), rtol=1e-5, atol=1e-7)


def test_an_unknown_backend_is_refused_by_name(box_grid):
    with pytest.raises(ValueError, match="projector.backend.*'gpu'"):
        make_operator("gpu", box_grid, random_rays(box_grid, 3), torch.arange(5))


# --------------------------------------------------------------------------- rendering


def test_camera_rays_keep_masked_pixels_with_their_flat_index(box_grid):
    H, W = 10, 12
    cams = ring_of_cameras(2, W, H, target=box_grid.index_to_world(torch.tensor([3.5, 5.5, 2.5])))
    masks = torch.zeros(2, H, W, dtype=torch.bool)
    masks[0, 3, 4] = masks[1, 9, 11] = masks[1, 0, 0] = True
    rays, flat = camera_rays(cams, masks)
    assert flat.tolist() == [3 * W + 4, H * W + 0, H * W + 9 * W + 11]
    uv = pixel_centers(H, W)[None].expand(2, -1, -1).contiguous()
    origins, dirs = pixel_rays(cams, uv)
    assert torch.allclose(rays.directions, dirs.reshape(-1, 3)[flat])
    assert torch.allclose(rays.origins, origins.reshape(-1, 3)[flat])


def test_render_of_an_empty_volume_is_black(box_grid):
    cams = ring_of_cameras(3, 24, 20, target=[0.2, 0.95, 1.375])
    images = render_image(torch.zeros(2, *box_grid.shape), box_grid, cams)
    assert images.shape == (3, 2, 20, 24)
    assert images.abs().max() == 0


def test_one_bright_voxel_lights_only_the_pixels_whose_rays_pass_near_it(box_grid):
    H, W = 20, 24
    cams = ring_of_cameras(3, W, H, target=[0.2, 0.95, 1.375])
    k, j, i = 3, 6, 4
    volume = torch.zeros(1, *box_grid.shape)
    volume[0, k, j, i] = 5.0
    images = render_image(volume, box_grid, cams)  # (3, 1, H, W)
    rays, _ = camera_rays(cams)
    centre = box_grid.centers()[k, j, i]
    w = centre - rays.origins
    distance = ((w**2).sum(-1) - (w * rays.directions).sum(-1) ** 2).clamp_min(0).sqrt()
    lit = images.reshape(-1) > 0
    side = 0.125
    assert lit.any()
    assert (distance[lit] < math.sqrt(3) * side + 1e-4).all()  # the hat's support: a 2-voxel cube
    assert lit[distance < 0.25 * side].all()
    assert images.min() >= 0


# --------------------------------------------------------------------------- support box


def test_support_box_bounds_where_the_interpolant_can_be_nonzero(box_grid):
    voxel_index = torch.tensor([box_grid.shape[2] * (box_grid.shape[1] * 2 + 5) + 3,
                                box_grid.shape[2] * (box_grid.shape[1] * 4 + 8) + 6])  # (k,j,i)=(2,5,3),(4,8,6)
    lo, hi = support_box(box_grid, voxel_index)
    size = box_grid.voxel_size()
    assert torch.allclose(lo, box_grid.lo() + (torch.tensor([3.0, 5.0, 2.0]) - 0.5) * size)
    assert torch.allclose(hi, box_grid.lo() + (torch.tensor([6.0, 8.0, 4.0]) + 1.5) * size)
    full_lo, full_hi = march_box(box_grid)
    everything = support_box(box_grid, torch.arange(box_grid.num_voxels))
    assert torch.allclose(everything[0], full_lo) and torch.allclose(everything[1], full_hi)
    # a volume living on those voxels samples to zero everywhere outside the box
    volume = torch.zeros(1, box_grid.num_voxels)
    volume[0, voxel_index] = 1.0
    volume = volume.reshape(1, *box_grid.shape)
    g = torch.Generator().manual_seed(0)
    pts = full_lo + torch.rand(4000, 3, generator=g) * (full_hi - full_lo)
    outside = ((pts < lo) | (pts > hi)).any(-1)
    coords = box_grid.world_to_normalized(pts).reshape(1, 1, 1, -1, 3)
    vals = F.grid_sample(volume[None], coords, align_corners=False).reshape(-1)
    assert outside.any() and (vals[outside] == 0).all()
    assert (vals[~outside] > 0).any()


def narrowed_case(grid: VoxelGrid, step: float):
    """Line integrals of a density living on a sub-block of voxels, marched over the full box
    and over its support box."""
    g = torch.Generator().manual_seed(0)
    volume = torch.zeros(3, *grid.shape)
    volume[:, 1:4, 3:8, 2:6] = torch.rand(3, 3, 5, 4, generator=g)
    box = support_box(grid, volume.sum(0).reshape(-1).nonzero().squeeze(1))
    rays = random_rays(grid, 300)
    return integrate_dense(volume, grid, rays, step), integrate_dense(volume, grid, rays, step, box)


def test_support_box_narrowing_gives_the_same_integrals_as_the_full_march(box_grid):
    full, narrow = narrowed_case(box_grid, 0.5)
    assert (full - narrow).abs().max() <= 1e-5 * full.abs().max()


def test_packed_samples_are_the_padded_march_without_its_padding_and_move_into_a_frame(box_grid):
    """Packed samples hold the real samples of :func:`ray_samples` bit for bit; with a
    ``frame`` their points are those points in the grid's voxel-index or grid_sample frame."""
    rays = random_rays(box_grid, 50, seed=3)
    points, length = ray_samples(rays, box_grid, 0.5)
    keep = length > 0
    blocks = list(packed_samples(rays, box_grid, 0.5, chunk=300))
    assert len(blocks) > 1  # the chunk splits the rays
    packed = torch.cat([b.points for _, b in blocks])
    assert torch.equal(packed, points[keep]) and torch.equal(torch.cat([b.length for _, b in blocks]), length[keep])
    for frame, to_frame in ((box_grid.index_frame(), box_grid.world_to_index),
                            (box_grid.normalized_frame(), box_grid.world_to_normalized)):
        moved = torch.cat([b.points for _, b in packed_samples(rays, box_grid, 0.5, chunk=300, frame=frame)])
        torch.testing.assert_close(moved, to_frame(points[keep]), atol=1e-5, rtol=1e-5)


def full_march(volume: torch.Tensor, grid: VoxelGrid, cams) -> torch.Tensor:
    """Every pixel of every camera marched through the whole box: (B, C, H, W)."""
    B, H, W = cams.batch_size, int(cams.height[0]), int(cams.width[0])
    rays, _ = camera_rays(cams)
    pix = integrate_dense(volume, grid, rays)
    return pix.T.reshape(volume.shape[0], B, H, W).transpose(0, 1)


@pytest.mark.parametrize("where", ["random", "edge", "block boundary"])
def test_a_render_marches_only_its_footprint_and_equals_the_full_march(box_grid, where):
    """Pixels outside the footprint of the density's nonzeros render exactly 0, so the render
    that skips them is the full march, bit for bit; the footprint is much smaller than the image."""
    cams = ring_of_cameras(4, 64, 48, target=[0.2, 0.95, 1.375], focal=40.0)
    volume = torch.zeros(2, *box_grid.shape)
    if where == "random":
        g = torch.Generator().manual_seed(5)
        volume[:, 1:4, 2:6, 1:5] = torch.rand(2, 3, 4, 4, generator=g)
    elif where == "edge":
        volume[:, 0, 11, 7] = 1.0  # a corner voxel: the interpolant reaches half a voxel outside the box
    else:
        volume[:, 2, 5, 3] = 1.0  # the last voxel of a 2-voxel block, next to the following block
    full = full_march(volume, box_grid, cams)
    assert torch.equal(render_image(volume, box_grid, cams), full)
    seen = footprint(volume.abs().sum(0) > 0, box_grid, cams)
    lit = full.abs().sum(1) > 0
    assert lit.any() and bool(seen[lit].all()) and float(seen.float().mean()) < 0.5


def test_a_camera_with_the_density_behind_its_centre_plane_keeps_every_pixel(box_grid):
    from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras

    inside = torch.tensor([0.2, 0.95, 1.375])  # the box centre: half the density is behind the camera
    cams = make_cameras(intrinsics_matrix(20.0, 20.0, 12.0, 10.0)[None],
                        look_at(inside[None], torch.tensor([[0.2, 0.95, 3.0]])), 20, 24)
    volume = torch.ones(1, *box_grid.shape)
    assert bool(footprint(volume[0] > 0, box_grid, cams).all())
    assert torch.equal(render_image(volume, box_grid, cams), full_march(volume, box_grid, cams))
    assert not footprint(torch.zeros(box_grid.shape, dtype=torch.bool), box_grid, cams).any()


def test_a_render_takes_the_pixels_an_operator_rendered_and_marches_only_the_rest(box_grid, monkeypatch):
    """The training views' silhouette pixels come from the assembled operator (A x: the march's
    own weights), so a scoring render marches only the footprint's other pixels."""
    from flamerecon.operators import projector

    cams = ring_of_cameras(3, 40, 30, target=[0.2, 0.95, 1.375], focal=28.0)
    voxel_index = random_hull(box_grid, seed=31)
    x = torch.rand(voxel_index.numel(), 2, generator=torch.Generator().manual_seed(32))
    volume = box_grid.dense(x, voxel_index)
    full = render_image(volume, box_grid, cams)
    masks = torch.zeros(3, 30, 40, dtype=torch.bool)
    masks[:, 5:25, 8:30] = True  # the "silhouettes": the operator's rows
    rays, flat = camera_rays(cams, masks)
    known = (flat, assemble(box_grid, rays, voxel_index).forward(x))
    marched = []
    integrate = projector.integrate_dense
    monkeypatch.setattr(projector, "integrate_dense", lambda v, g, r, *a, **k: (marched.append(len(r)),
                                                                                 integrate(v, g, r, *a, **k))[1])
    given = render_image(volume, box_grid, cams, known=known)
    assert torch.allclose(given, full, rtol=1e-5, atol=1e-6)
    seen = footprint(volume.abs().sum(0) > 0, box_grid, cams).reshape(-1)
    rest = seen.clone()
    rest[flat] = False
    assert marched == [int(rest.sum())] and marched[0] < 0.5 * int(seen.sum())
