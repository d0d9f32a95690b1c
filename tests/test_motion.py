"""Motion compensation (:mod:`flamerecon.dynamics.motion`, :mod:`flamerecon.operators.warp`): the
sparse warp is the dense one, a known constant motion is recovered, the composite operator's
adjoint passes the dot test, and on the moving synthetic flame a window does not lose held-out
PSNR against the single frame."""

from __future__ import annotations

import pytest
import torch

import flamerecon as fr
from flamerecon.dynamics.motion import MotionOptions, estimate_displacement, reconstruct_motion
from flamerecon.errors import ArgumentError
from flamerecon.operators import CsrOperator, dottest
from flamerecon.operators.warp import ComposedOperator, RowStack, warp_matrix, warp_volume

SHAPE = (14, 18, 16)  # (nz, ny, nx)


def blobs() -> torch.Tensor:
    """Two Gaussian blobs (1, nz, ny, nx), away from the border."""
    z, y, x = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in SHAPE], indexing="ij")
    return (torch.exp(-((x - 8) ** 2 + (y - 8) ** 2 + (z - 7) ** 2) / 8)
            + 0.6 * torch.exp(-((x - 6) ** 2 + (y - 11) ** 2 + (z - 8) ** 2) / 4))[None]


def constant(dx: float, dy: float, dz: float) -> torch.Tensor:
    return torch.tensor([dx, dy, dz]).reshape(3, 1, 1, 1).expand(3, *SHAPE).clone()


def test_the_sparse_warp_is_the_dense_warp():
    g = torch.Generator().manual_seed(0)
    u = 1.5 * torch.randn(3, *SHAPE, generator=g)
    volume = torch.rand(2, *SHAPE, generator=g)
    every = torch.arange(volume[0].numel())
    W = warp_matrix(u, every, every)
    dense = warp_volume(volume, u).reshape(2, -1).T
    assert torch.allclose(W.forward(volume.reshape(2, -1).T.contiguous()), dense, atol=1e-5)


def test_a_constant_motion_is_recovered():
    truth = (1.3, -0.7, 0.4)
    source = blobs()
    target = warp_volume(source, constant(*truth))
    found = estimate_displacement(source, target, MotionOptions(control=4, iters=30))
    inside = target[0] > 0.1
    mean = [float(found.u[c][inside].mean()) for c in range(3)]
    assert mean == pytest.approx(truth, abs=0.05)
    assert found.shift == (1, -1, 0)  # the whole-cell start
    assert found.residual < 0.01 * found.residual_shift < found.residual_none


def test_a_constant_motion_is_recovered_from_images():
    truth = (-1.2, 0.6, 0.0)
    source = blobs()
    index = (source[0].reshape(-1) > -1).nonzero().squeeze(1)
    n = int(index.numel())
    identity = CsrOperator.from_coo(torch.arange(n), torch.arange(n), torch.ones(n), (n, n))
    images = warp_volume(source, constant(*truth)).reshape(1, -1).T.contiguous()
    # the neighbour's density is given as the source itself (its shift is 0): only the images move
    found = estimate_displacement(source, source, MotionOptions(control=4, iters=30, fit_to="images"),
                                  data=(identity, images, index))
    inside = images[:, 0].reshape(SHAPE) > 0.1
    assert [float(found.u[c][inside].mean()) for c in range(3)] == pytest.approx(truth, abs=0.1)


def test_the_composite_operator_passes_the_dot_test():
    g = torch.Generator().manual_seed(1)
    volume = blobs()[0].reshape(-1)
    src = (volume > 0.05).nonzero().squeeze(1)
    u = constant(0.7, 1.4, -0.3) + 0.3 * torch.randn(3, *SHAPE, generator=g)
    dst = (warp_volume(blobs(), u)[0].reshape(-1) > 0.03).nonzero().squeeze(1)
    W = warp_matrix(u, src, dst)

    def projector(m: int, rows: int) -> CsrOperator:
        dense = torch.rand(rows, m, generator=g) * (torch.rand(rows, m, generator=g) < 0.1)
        r, c = dense.nonzero(as_tuple=True)
        return CsrOperator.from_coo(r, c, dense[r, c], (rows, m))

    A_t, A_s = projector(int(src.numel()), 40), projector(int(dst.numel()), 50)
    identity = CsrOperator.from_coo(torch.arange(src.numel()), torch.arange(src.numel()),
                                    torch.ones(src.numel()), (src.numel(), src.numel()))
    stack = RowStack([ComposedOperator(A_t, identity), ComposedOperator(A_s, W, 0.5 ** 0.5)])
    assert stack.shape == (90, int(src.numel()))
    dottest(W, rtol=1e-5)
    dottest(stack, rtol=1e-5)


def test_motion_options_are_checked():
    with pytest.raises(ArgumentError, match="motion.window"):
        MotionOptions(window=4)
    with pytest.raises(ArgumentError, match="motion.decay"):
        MotionOptions(decay=1.5)
    with pytest.raises(ArgumentError, match="motion.fit_to"):
        MotionOptions(fit_to="flow")


SYNTHETIC = {"name": "synthetic", "width": 96, "height": 72, "n_cameras": 5, "phantom_resolution": 48}


def test_a_window_on_the_moving_synthetic_flame_does_not_lose_heldout_psnr():
    # every third frame: the flame's turbulence rises about 2 cells of the 24-cell grid between them
    scenes = [fr.load_scene({**SYNTHETIC, "frame": t}) for t in (0, 3, 6)]
    options = fr.preset("synthetic", "solver=tv", "grid.resolution=24", "solver.max_iters=100", "device=cpu")
    single = reconstruct_motion(scenes, options, MotionOptions(window=1), target=1)
    assert [f.setup.scene.meta["frame"] for f in single.frames] == [3]
    assert torch.equal(single.x, single.frames[0].fit.result.x)
    window = reconstruct_motion(scenes, options, MotionOptions(window=3, decay=1.0, control=4), target=1)
    assert sorted(window.displacements) == [0, 2]
    assert all(d.residual < d.residual_none for d in window.displacements.values())
    psnr = [s.score()["heldout"]["cam04"]["psnr"] for s in (single, window)]
    assert psnr[1] > psnr[0] - 0.1, psnr
