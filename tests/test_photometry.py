"""Linearizing recorded values and fitting a per-camera gain and offset."""

from __future__ import annotations

import pytest
import torch

from flamerecon.geometry.photometry import (
    apply_gain_offset,
    delinearize,
    fit_gain_offset,
    fit_gain_offset_rows,
    linearize,
    normalize_gains,
    remove_gain_offset,
    srgb_to_linear,
)


def test_linearize_black_level_and_gamma():
    v = torch.tensor([0.0, 0.1, 0.2, 0.6, 1.0]).reshape(1, 1, 1, 5)
    out = linearize(v, gamma=2.0, black_level=0.2)
    expected = torch.tensor([0.0, 0.0, 0.0, 0.5**2, 1.0]).reshape(1, 1, 1, 5)
    torch.testing.assert_close(out, expected)
    assert linearize(v) is v  # identity by default
    torch.testing.assert_close(linearize(v, gamma="srgb"), srgb_to_linear(v))
    assert float(srgb_to_linear(torch.tensor(0.5))) == pytest.approx(0.21404, abs=1e-4)


@pytest.mark.parametrize("gamma, black", [(2.2, 0.0), ("srgb", 0.0), (1.0, 0.1), (2.0, 0.05)])
def test_delinearize_returns_recorded_values_at_or_above_the_black_level(gamma, black):
    recorded = torch.linspace(black, 1.0, 41).reshape(1, 1, 1, 41)
    back = delinearize(linearize(recorded, gamma, black), gamma, black)
    torch.testing.assert_close(back, recorded, atol=1e-6, rtol=0)


def test_scores_are_taken_in_recorded_units(small_scene):
    """A scene linearized with gamma 2.2 and a black level scores a render as the camera would
    have recorded it: PSNR of 0.05 + 0.95 render ** (1/2.2) against the recorded image (not
    of the linear values, nor of an image rebuilt from them)."""
    from dataclasses import replace

    from flamerecon.evaluate.metrics import psnr
    from flamerecon.evaluate.scores import score_views

    recorded = small_scene.images
    scene = replace(small_scene, images=linearize(recorded, 2.2, 0.05), recorded_images=recorded,
                    response={"gamma": 2.2, "black_level": 0.05})
    render = scene.images[:1] * 0.8  # a render 20% too dark in linear units
    got = score_views(render, scene, [0])[scene.views[0]]
    expected = psnr(0.05 + 0.95 * render[0] ** (1 / 2.2), recorded[0])
    assert got["psnr"] == pytest.approx(expected, abs=1e-4)
    assert got["psnr"] != pytest.approx(psnr(render[0], scene.images[0]), abs=0.1)
    assert got["psnr_black"] == pytest.approx(psnr(torch.zeros_like(recorded[0]), recorded[0]))


@pytest.mark.parametrize("gamma, black", [(0.0, 0.0), ("log", 0.0), (1.0, 1.0)])
def test_linearize_rejects_bad_settings(gamma, black):
    with pytest.raises(ValueError, match="scene"):
        linearize(torch.zeros(1, 1, 2, 2), gamma=gamma, black_level=black)


def test_gain_offset_fit_recovers_each_camera():
    g = torch.Generator().manual_seed(1)
    rendered = torch.rand(3, 1, 8, 10, generator=g)
    gain, offset = torch.tensor([0.8, 1.0, 1.25]), torch.tensor([0.02, 0.0, -0.01])
    captured = apply_gain_offset(rendered, gain, offset)
    mask = torch.ones(3, 8, 10, dtype=torch.bool)
    mask[:, :2] = False
    captured[:, :, :2] = 5.0  # outliers outside the mask must not count
    fit_g, fit_o = fit_gain_offset(rendered, captured, mask)
    torch.testing.assert_close(fit_g, gain, atol=1e-5, rtol=0)
    torch.testing.assert_close(fit_o, offset, atol=1e-5, rtol=0)
    fit_g, fit_o = fit_gain_offset(
        rendered[:, :, 2:], captured[:, :, 2:] - offset.reshape(3, 1, 1, 1), fit_offset=False
    )
    torch.testing.assert_close(fit_g, gain, atol=1e-5, rtol=0)
    assert bool((fit_o == 0).all())
    torch.testing.assert_close(
        remove_gain_offset(captured, gain, offset)[:, :, 2:], rendered[:, :, 2:]
    )


def test_gain_offset_fit_on_stacked_rows():
    g = torch.Generator().manual_seed(2)
    view = torch.tensor([0] * 50 + [2] * 40)  # camera 1 has no rows
    predicted = torch.rand(90, 1, generator=g)
    gain, offset = torch.tensor([0.9, 1.0, 1.2]), torch.tensor([0.01, 0.0, -0.02])
    captured = predicted * gain[view, None] + offset[view, None]
    fit_g, fit_o = fit_gain_offset_rows(predicted, captured, view, 3)
    torch.testing.assert_close(fit_g, gain, atol=1e-5, rtol=0)
    torch.testing.assert_close(fit_o, offset, atol=1e-5, rtol=0)
    normalized = normalize_gains(torch.tensor([0.5, 2.0, 1.0]))
    torch.testing.assert_close(normalized, torch.tensor([0.5, 2.0, 1.0]))
    torch.testing.assert_close(normalize_gains(torch.tensor([2.0, 8.0])), torch.tensor([0.5, 2.0]))
