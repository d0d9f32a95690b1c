"""Camera conventions, pinned down by example.

- world -> camera extrinsics in the OpenCV frame (x right, y down, z forward);
- pixel (u, v) covers [u, u+1) x [v, v+1), its centre is (u + 0.5, v + 0.5);
- NeRF/Blender ``transform_matrix`` is camera -> world in the OpenGL frame (y up, z back).
"""

from __future__ import annotations

import math

import pytest
import torch

from flamerecon.geometry.cameras import (
    camera_centers,
    intrinsics_matrix,
    look_at,
    make_cameras,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_centers,
    pixel_rays,
    project_points,
)

W, H = 32, 24


def one_camera(eye, target, width=W, height=H, focal=40.0, up=(0.0, 1.0, 0.0)):
    """A single look-at camera with the principal point at the image centre."""
    K = intrinsics_matrix(focal, focal, width / 2, height / 2)
    return make_cameras(K, look_at([eye], [target], up), height, width)


def random_rotation(g: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def test_pixel_centres_sit_at_half_integers():
    uv = pixel_centers(H, W)
    assert uv.shape == (H * W, 2)
    u, v = 3, 5
    assert uv[v * W + u].tolist() == [3.5, 5.5]  # row-major: v slowest


def test_a_point_on_the_ray_through_a_pixel_centre_projects_to_that_centre():
    cams = one_camera(eye=(0.3, 0.8, 2.5), target=(0.0, 0.5, 0.0))
    uv = torch.tensor([[[3.5, 5.5]]])  # centre of pixel (3, 5)
    origins, dirs = pixel_rays(cams, uv)
    for t in (0.5, 2.0, 7.0):
        point = origins[0] + t * dirs[0]
        pix, depth = project_points(cams, point)
        assert torch.allclose(pix[0, 0], torch.tensor([3.5, 5.5]), atol=1e-4)
        assert depth[0, 0] > 0


def test_project_then_unproject_at_the_same_depth_gives_the_point_back():
    cams = one_camera(eye=(-1.0, 2.0, 3.0), target=(0.1, 0.2, -0.1))
    g = torch.Generator().manual_seed(0)
    xyz = torch.randn(50, 3, generator=g) * 0.4
    uv, depth = project_points(cams, xyz)
    back = cams.unproject(uv, depth[..., None])
    assert torch.allclose(back[0], xyz, atol=1e-4)


def test_optical_axis_meets_the_principal_point():
    cams = one_camera(eye=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0))
    uv, depth = project_points(cams, torch.zeros(1, 3))
    assert torch.allclose(uv[0, 0], torch.tensor([W / 2, H / 2]), atol=1e-5)
    assert depth[0, 0].item() == pytest.approx(4.0, abs=1e-5)


@pytest.mark.parametrize("eye", [(0.0, 0.3, 3.0), (2.0, 1.0, -1.5), (-2.5, -0.5, 0.5)])
def test_look_at_world_up_is_image_up_and_camera_right_is_larger_u(eye):
    target = torch.tensor([0.1, 0.4, -0.2])
    cams = one_camera(eye=eye, target=target.tolist())
    forward = torch.nn.functional.normalize(target - torch.tensor(eye), dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, torch.tensor([0.0, 1.0, 0.0])), dim=0)
    pts = torch.stack([target, target + torch.tensor([0.0, 0.1, 0.0]), target + 0.1 * right])
    uv, depth = project_points(cams, pts)
    centre, above, to_the_right = uv[0]
    assert torch.allclose(centre, torch.tensor([W / 2, H / 2]), atol=1e-4)
    assert above[1] < centre[1] - 0.5  # up in the world is up (smaller v) in the image
    assert abs(above[0] - centre[0]) < 1e-3
    assert to_the_right[0] > centre[0] + 0.5  # the camera's right is larger u
    assert (depth > 0).all()


def test_camera_centres_are_the_look_at_eyes_and_equal_minus_Rt_t():
    eyes = torch.tensor([[0.0, 0.3, 3.0], [2.0, 1.0, -1.5], [-2.5, -0.5, 0.5]])
    E = look_at(eyes, torch.zeros(3, 3))
    K = intrinsics_matrix(40.0, 40.0, W / 2, H / 2).expand(3, 3, 3)
    cams = make_cameras(K, E, H, W)
    centres = camera_centers(cams)
    assert torch.allclose(centres, eyes, atol=1e-5)
    R, t = E[:, :3, :3].double(), E[:, :3, 3].double()
    assert torch.allclose(centres.double(), -(R.transpose(1, 2) @ t[..., None])[..., 0], atol=1e-5)
    # the centre maps to the camera frame's origin
    homog = torch.cat([centres, torch.ones(3, 1)], 1)
    assert torch.allclose((E @ homog[..., None])[:, :3, 0], torch.zeros(3, 3), atol=1e-5)


def test_pixel_rays_are_unit_start_at_the_centre_and_pass_through_their_pixels():
    eyes = torch.tensor([[0.0, 0.3, 3.0], [2.0, 1.0, -1.5]])
    K = intrinsics_matrix(40.0, 40.0, W / 2, H / 2).expand(2, 3, 3)
    cams = make_cameras(K, look_at(eyes, torch.zeros(2, 3)), H, W)
    uv = pixel_centers(H, W)[None].expand(2, -1, -1).contiguous()
    origins, dirs = pixel_rays(cams, uv)
    assert origins.shape == dirs.shape == (2, H * W, 3)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(2, H * W), atol=1e-5)
    assert torch.allclose(origins, eyes[:, None].expand(2, H * W, 3), atol=1e-5)
    for b in range(2):
        cam = make_cameras(K[b:b + 1], cams.extrinsics[b:b + 1], H, W)
        pix, depth = project_points(cam, origins[b] + 1.7 * dirs[b])
        assert torch.allclose(pix[0], uv[b], atol=1e-3)
        assert (depth > 0).all()


def test_nerf_camera_on_the_z_axis_sees_the_origin_at_the_image_centre():
    # NeRF/Blender: camera -> world, OpenGL axes; identity rotation looks down world -z.
    c2w = torch.eye(4)
    c2w[2, 3] = 3.0
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    K = intrinsics_matrix(40.0, 40.0, W / 2, H / 2)
    cams = make_cameras(K, w2c[None], H, W)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.2, 0.0, 0.0]])
    uv, depth = project_points(cams, pts)
    assert torch.allclose(uv[0, 0], torch.tensor([W / 2, H / 2]), atol=1e-5)
    assert depth[0, 0].item() == pytest.approx(3.0, abs=1e-5)
    assert uv[0, 1, 1] < H / 2  # NeRF camera y is up: world +y appears above the centre
    assert uv[0, 2, 0] > W / 2  # NeRF camera x is right
    assert torch.allclose(camera_centers(cams)[0], torch.tensor([0.0, 0.0, 3.0]), atol=1e-6)


def test_nerf_c2w_to_opencv_w2c_and_back_is_the_identity():
    g = torch.Generator().manual_seed(1)
    for _ in range(5):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = random_rotation(g)
        c2w[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64) * 3
        w2c = opengl_c2w_to_opencv_w2c(c2w)
        assert torch.allclose(opencv_w2c_to_opengl_c2w(w2c).double(), c2w, atol=1e-5)
        # OpenCV forward (+z) is OpenGL backward (-z); the centre is the c2w translation
        R = w2c[:3, :3].double()
        assert torch.allclose(R[2], -c2w[:3, 2], atol=1e-5)
        assert torch.allclose(R[1], -c2w[:3, 1], atol=1e-5)
        assert torch.allclose(R[0], c2w[:3, 0], atol=1e-5)
        centre = -(R.T @ w2c[:3, 3].double())
        assert torch.allclose(centre, c2w[:3, 3], atol=1e-4)


def test_a_batch_of_nerf_cameras_converts_in_one_call():
    angles = torch.linspace(0, 2 * math.pi, 5)[:-1]
    c2w = torch.eye(4).repeat(4, 1, 1)
    c, s = torch.cos(angles), torch.sin(angles)
    c2w[:, 0, 0], c2w[:, 0, 2], c2w[:, 2, 0], c2w[:, 2, 2] = c, s, -s, c  # rotate about y
    c2w[:, :3, 3] = 3.0 * c2w[:, :3, 2]  # on a ring, each looking at the origin
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    assert w2c.shape == (4, 4, 4)
    K = intrinsics_matrix(40.0, 40.0, W / 2, H / 2).expand(4, 3, 3)
    uv, depth = project_points(make_cameras(K, w2c, H, W), torch.zeros(1, 3))
    assert torch.allclose(uv[:, 0], torch.tensor([W / 2, H / 2]).expand(4, 2), atol=1e-4)
    assert torch.allclose(depth[:, 0], torch.full((4,), 3.0), atol=1e-5)
