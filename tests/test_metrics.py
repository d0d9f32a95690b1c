"""Image and volume quality measures against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

from flamerecon.evaluate.metrics import psnr, resample_to, ssim, volume_errors


def test_psnr_matches_a_hand_computed_value():
    target = torch.tensor([[[0.1, 0.2], [0.3, 0.4]]])  # (1, 2, 2)
    pred = torch.zeros_like(target)
    mse = (0.01 + 0.04 + 0.09 + 0.16) / 4  # 0.075
    assert psnr(pred, target) == pytest.approx(10 * math.log10(1 / mse), abs=1e-6)  # float32 inputs
    assert psnr(pred, target) == pytest.approx(11.2494, abs=1e-4)
    # max_val rescales: the same error on a 0..255 scale
    assert psnr(pred * 255, target * 255, max_val=255.0) == pytest.approx(11.2494, abs=1e-4)


def test_psnr_is_over_every_channel_and_pixel_and_clips_the_prediction():
    target = torch.full((3, 4, 5), 0.5)
    pred = target.clone()
    pred[1, 2, 3] = 0.9  # one wrong value among 60
    assert psnr(pred, target) == pytest.approx(10 * math.log10(60 / 0.16), abs=1e-6)
    assert psnr(target, target) == math.inf
    ones = torch.ones(3, 4, 5)
    assert psnr(ones * 1.7, ones) == math.inf  # the prediction is clipped to [0, 1]


def test_ssim_is_one_for_identical_images_and_drops_with_noise():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 32, 32, generator=g)
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-5)
    a = ssim((image + 0.05 * torch.randn(3, 32, 32, generator=g)).clamp(0, 1), image)
    b = ssim((image + 0.2 * torch.randn(3, 32, 32, generator=g)).clamp(0, 1), image)
    assert 1.0 > a > b


def blob(shape=(6, 8, 10), lo=(1, 2, 3), hi=(4, 5, 6)) -> torch.Tensor:
    v = torch.zeros(3, *shape)
    v[:, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = torch.tensor([1.0, 0.6, 0.3])[:, None, None, None]
    return v


def test_volume_errors_of_the_truth_itself_are_perfect():
    truth = blob()
    assert volume_errors(truth, truth) == {"rel_l2": 0.0, "iou": 1.0}


def test_volume_errors_of_scaled_shifted_and_empty_densities():
    truth = blob()
    twice = volume_errors(2 * truth, truth)
    assert twice["rel_l2"] == pytest.approx(1.0) and twice["iou"] == 1.0
    # a 3x3x3 block shifted by one voxel along x: overlap 18, union 36
    shifted = volume_errors(blob(lo=(1, 2, 4), hi=(4, 5, 7)), truth)
    assert shifted["iou"] == pytest.approx(18 / 36)
    assert shifted["rel_l2"] == pytest.approx(math.sqrt(2 * 9 / 27))
    empty = volume_errors(torch.zeros_like(truth), truth)
    assert empty == {"rel_l2": 1.0, "iou": 0.0}


def test_resample_to_keeps_a_shape_it_already_has_and_preserves_the_mean():
    g = torch.Generator().manual_seed(0)
    volume = torch.rand(3, 8, 12, 8, generator=g)
    assert resample_to(volume, (8, 12, 8)) is volume
    half = resample_to(volume, (4, 6, 4))
    assert half.shape == (3, 4, 6, 4)
    assert torch.allclose(half.mean((1, 2, 3)), volume.mean((1, 2, 3)), atol=1e-6)
    # each coarse cell is the average of the 2x2x2 fine cells it covers
    assert half[1, 2, 3, 1].item() == pytest.approx(volume[1, 4:6, 6:8, 2:4].mean().item(), abs=1e-6)


def ramp(n_in: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell values of f(x) = x on [0, 1] at n_in cells resampled to n_out, and the exact
    cell averages (the coarse cell centres)."""
    x = (torch.arange(n_in, dtype=torch.float64) + 0.5) / n_in
    coarse = resample_to(x.expand(1, 2, 2, n_in).clone(), (2, 2, n_out))[0, 0, 0]
    return coarse, (torch.arange(n_out, dtype=torch.float64) + 0.5) / n_out


def test_resample_to_gives_exact_cell_averages_for_integer_ratios():
    coarse, exact = ramp(24, 8)
    assert torch.allclose(coarse, exact, atol=1e-12)


def test_resample_to_gives_exact_cell_averages_for_non_integer_ratios():
    # reference: split both grids into their least common multiple of cells (21 * 11), where
    # each fine cell is constant, and average blocks of 21 -> exact coarse cell averages
    fine = torch.rand(21, dtype=torch.float64)
    coarse = resample_to(fine.expand(1, 2, 2, 21).clone(), (2, 2, 11))[0, 0, 0]
    exact = fine.repeat_interleave(11).reshape(11, 21).mean(1)
    assert torch.allclose(coarse, exact, atol=1e-12)
    # and the old adaptive pooling would not pass this
    pooled = torch.nn.functional.adaptive_avg_pool1d(fine[None, None], 11)[0, 0]
    assert not torch.allclose(pooled, exact, atol=1e-3)


def test_detail_correlation_sees_fine_structure_and_nothing_else():
    """The detail correlation: 1 for the image itself and any gain/offset of it (exposure is not
    detail), lower the more the render is blurred, NaN where a band is flat, and restricted to
    the mask when given."""
    import kornia

    from flamerecon.evaluate.metrics import detail_correlation

    g = torch.Generator().manual_seed(3)
    image = kornia.filters.gaussian_blur2d(torch.rand(1, 3, 48, 40, generator=g), (5, 5), (1.0, 1.0))[0]
    assert detail_correlation(image, image) == pytest.approx(1.0)
    assert detail_correlation(0.5 * image + 0.2, image) == pytest.approx(1.0)
    blurred = [kornia.filters.gaussian_blur2d(image[None], (k, k), (s, s))[0] for k, s in ((7, 1.0), (13, 2.0), (25, 4.0))]
    scores = [detail_correlation(b, image) for b in blurred]
    assert 1.0 > scores[0] > scores[1] > scores[2]
    assert scores[2] < 0.3  # a blob keeps almost none of the wisps
    assert math.isnan(detail_correlation(torch.full_like(image, 0.3), image))
    other = image.clone()
    other[:, :, 20:] = torch.rand(3, 48, 20, generator=g)
    left = torch.zeros(48, 40, dtype=torch.bool)
    left[:, :14] = True  # the left half, away from the seam that the blur mixes across
    assert detail_correlation(other, image, mask=left) == pytest.approx(1.0)
    assert detail_correlation(other, image) < 0.9


def test_the_detail_band_keeps_its_size_in_native_pixels():
    from types import SimpleNamespace

    from flamerecon.evaluate.scores import detail_sigma

    def scene_of(height, width):  # detail_sigma reads the image size only
        return SimpleNamespace(images=torch.zeros(1, 1, height, width))

    assert detail_sigma(scene_of(480, 270)) == 2.0  # ScalarFlow at 1/4
    assert detail_sigma(scene_of(960, 540)) == 4.0  # at 1/2: the same structures
    assert detail_sigma(scene_of(1920, 1080)) == 8.0
    assert detail_sigma(scene_of(240, 320)) == pytest.approx(2.0 * 240 / 270)  # the synthetic flame


def test_the_detail_band_of_an_image_smaller_than_its_kernel_is_defined():
    from flamerecon.evaluate.metrics import detail_band

    image = torch.rand(3, 6, 5)
    band = detail_band(image, sigma=8.0)  # a 49-px kernel on a 6x5 image
    assert band.shape == image.shape and torch.isfinite(band).all() and band.abs().sum() > 0


@pytest.mark.parametrize("shape, sigma", [((1, 60, 80), 1.78), ((3, 48, 64), 2.0), ((2, 5, 7), 2.0), ((1, 90, 40), 8.0)])
def test_the_detail_band_is_the_image_less_its_reflected_gaussian_blur(shape, sigma):
    """The band against kornia's own Gaussian blur (reflect padding, kernel 2 ceil(3 sigma) + 1,
    at most 2 min(H, W) - 1), on images small enough that the kernel is cut."""
    import kornia

    from flamerecon.evaluate.metrics import detail_band

    image = torch.rand(shape, generator=torch.Generator().manual_seed(0))
    size = min(2 * math.ceil(3 * sigma) + 1, 2 * min(shape[-2:]) - 1)
    flat = image[None].double()
    expected = flat - kornia.filters.gaussian_blur2d(flat, (size, size), (sigma, sigma), border_type="reflect")
    band = detail_band(image, sigma)
    assert band.shape == image.shape
    assert float((band - expected[0]).abs().max()) <= 1e-12
