"""A camera's sensor noise, estimated from images: what a render's error against a capture
holds beyond the render's own spread (:mod:`flamerecon.evaluate.uncertainty`), since the
capture is the true image plus its noise.

The noise is modelled as signal-dependent (Poisson-Gaussian, as a photon-counting sensor
records): variance ``a + b I`` at recorded intensity ``I``, per channel. Each image is filtered by
Immerkær's kernel ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``, which cancels smooth structure and
answers white noise of variance ``s2`` with variance ``36 s2``; the pixels are binned by their
3x3 mean intensity, each bin's variance is read off the median of the squared responses (a
chi-square with one degree of freedom has median 0.4549: robust to the edges of the structure,
which are few), and ``a``, ``b`` are fitted to the bins by least squares weighted by their pixel
counts (both kept >= 0). J. Immerkær, "Fast noise variance estimation", CVIU 64(2), 1996.

Estimated on the training images only, the same for every camera of the rig: a held-out
camera's own image is never read.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

#: Immerkær's kernel: zero response to constant, linear and (separably) quadratic structure
KERNEL = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=torch.float64)
#: the kernel's gain on white noise's variance (the sum of its squared taps)
KERNEL_GAIN = 36.0
#: the median of a chi-square variable with one degree of freedom
CHI2_MEDIAN = 0.45493642311957283
#: intensity bins of the fit
BINS = 16
#: pixels a bin needs to enter the fit
MIN_PIXELS = 50


@dataclass(frozen=True)
class NoiseModel:
    """Variance ``a + b I`` (per channel, ``a``, ``b`` (C,) float64) of a recorded pixel of
    intensity ``I`` (recorded units, images in [0, 1])."""

    a: torch.Tensor
    b: torch.Tensor

    def variance(self, intensity: torch.Tensor) -> torch.Tensor:
        """The noise variance (..., C, H, W) of pixels recorded at ``intensity`` (..., C, H, W)."""
        shape = (-1, 1, 1)
        a, b = (t.to(intensity.device, torch.float64).reshape(shape) for t in (self.a, self.b))
        return (a + b * intensity.double().clamp_min(0)).to(intensity.dtype)

    def record(self) -> dict:
        return {"a": self.a.tolist(), "b": self.b.tolist(), "model": "a + b * intensity (recorded units)",
                "source": "the training images (Immerkaer's kernel, binned by intensity)"}


def noise_model(images: torch.Tensor) -> NoiseModel:
    """The :class:`NoiseModel` of ``images`` (V, C, H, W) in [0, 1], recorded units, each at least
    3 x 3 pixels; zero where they hold no noise (or too few pixels to tell)."""
    _, C, H, W = images.shape
    if H < 3 or W < 3:
        zero = torch.zeros(C, dtype=torch.float64)
        return NoiseModel(zero, zero.clone())
    a, b = [], []
    for c in range(C):  # one channel at a time, in float32: a full-resolution rig's images are large
        x = images[:, c:c + 1].detach().float().cpu()
        r2 = F.conv2d(x, KERNEL[None, None].float()).reshape(-1).pow(2)
        at = F.avg_pool2d(x, 3, stride=1).reshape(-1)
        del x
        edges = torch.linspace(float(at.min()), float(at.max()) + 1e-6, BINS + 1)
        which = torch.bucketize(at, edges[1:-1])
        rows = []
        for k in range(BINS):
            inside = which == k
            n = int(inside.sum())
            if n >= MIN_PIXELS:
                rows.append((float(at[inside].mean()), float(r2[inside].median()) / (KERNEL_GAIN * CHI2_MEDIAN), n))
        a_c, b_c = fit_line(rows)
        a.append(a_c)
        b.append(b_c)
    return NoiseModel(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64))


def fit_line(rows: list[tuple[float, float, int]]) -> tuple[float, float]:
    """``(a, b)`` >= 0 of ``variance = a + b intensity`` through the bins ``rows`` (intensity,
    variance, pixels), least squares weighted by pixels; one bin: ``(variance, 0)``."""
    if not rows:
        return 0.0, 0.0
    t = torch.tensor(rows, dtype=torch.float64)
    x, y, w = t[:, 0], t[:, 1], t[:, 2]
    if len(rows) == 1:
        return max(float(y[0]), 0.0), 0.0
    X = torch.stack([torch.ones_like(x), x], 1) * w.sqrt()[:, None]
    a, b = torch.linalg.lstsq(X, y * w.sqrt()).solution.tolist()
    if b < 0:  # no growth with intensity: a constant
        return max(float((w * y).sum() / w.sum()), 0.0), 0.0
    if a < 0:  # through the origin
        return 0.0, max(float((w * x * y).sum() / (w * x * x).sum()), 0.0)
    return a, b
