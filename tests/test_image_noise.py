"""The sensor noise a render's error against a capture holds (flamerecon.evaluate.image_noise):
a known signal-dependent noise is recovered from images whose structure the estimator must
ignore, noiseless structure reads as no noise, a held-out view is never read, and the predicted
spread against a capture adds the noise in variance."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

import flamerecon as fr
from flamerecon.evaluate.image_noise import NoiseModel, fit_line, noise_model
from flamerecon.evaluate.uncertainty import capture_sigma, training_noise


def smooth_images(V: int = 3, C: int = 2, H: int = 96, W: int = 128) -> torch.Tensor:
    """(V, C, H, W) in [0.05, 0.85]: broad blobs and ramps, nothing at the pixel scale."""
    y, x = torch.meshgrid(torch.linspace(-1, 1, H, dtype=torch.float64), torch.linspace(-1, 1, W, dtype=torch.float64),
                          indexing="ij")
    out = []
    for v in range(V):
        per_channel = []
        for c in range(C):
            cx, cy = 0.3 * math.cos(v + c), 0.3 * math.sin(2 * v + c)
            blob = torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 0.15)
            per_channel.append(0.05 + 0.6 * blob + 0.2 * (x + 1) / 2)
        out.append(torch.stack(per_channel))
    return torch.stack(out)


@pytest.mark.parametrize("a, b", [(1e-4, 0.0), (2e-5, 4e-4), (0.0, 1e-3)])
def test_a_known_signal_dependent_noise_is_recovered_beside_the_structure(a, b):
    clean = smooth_images()
    noise = torch.randn(clean.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    noisy = clean + (a + b * clean).sqrt() * noise
    found = noise_model(noisy)
    level = torch.tensor([0.1, 0.4, 0.7], dtype=torch.float64)
    for c in range(clean.shape[1]):
        want = a + b * level
        got = found.a[c] + found.b[c] * level
        torch.testing.assert_close(got, want, rtol=0.12, atol=3e-6)


def test_structure_without_noise_reads_as_none():
    found = noise_model(smooth_images())
    assert float(found.variance(torch.full((2, 4, 4), 0.5, dtype=torch.float64)).max()) < 1e-7


def test_images_too_small_or_flat_give_zero_noise():
    assert float(noise_model(torch.rand(1, 3, 2, 40)).a.abs().sum()) == 0.0
    flat = noise_model(torch.full((2, 1, 20, 20), 0.3))
    assert float(flat.a[0]) == 0.0 and float(flat.b[0]) == 0.0


def test_the_line_stays_nonnegative():
    assert fit_line([(0.1, 2e-4, 100), (0.5, 1e-4, 100)]) == pytest.approx((1.5e-4, 0.0))  # falling: a constant
    a, b = fit_line([(0.2, 1e-4, 100), (0.6, 5e-4, 100)])  # crosses zero below 0.1: through the origin
    assert a == 0.0 and b > 0
    assert fit_line([(0.3, 2e-4, 10)]) == (2e-4, 0.0) and fit_line([]) == (0.0, 0.0)


def test_the_held_out_view_is_never_read():
    scene = fr.load_scene("synthetic", width=48, height=36, n_cameras=4, phantom_resolution=24)
    before = training_noise(scene, [0, 1, 2])
    images = scene.images.clone()
    images[3] = torch.rand(images[3].shape)  # the held-out view made pure noise
    after = training_noise(replace(scene, images=images), [0, 1, 2])
    torch.testing.assert_close(after.a, before.a)
    torch.testing.assert_close(after.b, before.b)


def test_the_spread_against_a_capture_adds_the_noise_in_variance():
    scene = fr.load_scene("synthetic", width=48, height=36, n_cameras=4, phantom_resolution=24)
    rendered = torch.full((3, 6, 8), 0.25)
    sigma = torch.full((3, 6, 8), 0.03)
    noise = NoiseModel(torch.full((3,), 1e-4, dtype=torch.float64), torch.full((3,), 4e-4, dtype=torch.float64))
    got = capture_sigma(scene, rendered, sigma, noise)
    torch.testing.assert_close(got, torch.full((3, 6, 8), math.sqrt(0.03**2 + 1e-4 + 4e-4 * 0.25)))
    silent = NoiseModel(torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(capture_sigma(scene, rendered, sigma, silent), sigma)
