"""Image and volume quality measures."""

from __future__ import annotations

import math

import cv2
import kornia
import numpy as np
import torch


def psnr(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0) -> float:
    """PSNR in dB of one image (C, H, W) over the full frame; pred is clipped to [0, max_val]."""
    mse = float(((pred.clamp(0, max_val) - target) ** 2).double().mean())
    return math.inf if mse == 0 else 10.0 * math.log10(max_val**2 / mse)


#: the appearance-aligned PSNR is undefined (NaN) where either half of the captured image holds
#: less than this share of its light: a gain fitted on a dark half, or scored on one, says nothing
ALIGNED_MIN_SHARE = 0.2


def psnr_aligned(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0) -> float:
    """Appearance-aligned PSNR (NeRF in the Wild's protocol): one gain fitted by least squares
    on the left half of the image (C, H, W), PSNR on the right half; NaN where either half of
    ``target`` holds less than :data:`ALIGNED_MIN_SHARE` of its light. Not the headline score:
    it forgives a held-out camera's unknown exposure."""
    W = pred.shape[-1]
    left, right = slice(0, W // 2), slice(W // 2, W)
    light = float(target.double().clamp_min(0).sum())
    halves = (float(target[..., left].double().clamp_min(0).sum()), float(target[..., right].double().clamp_min(0).sum()))
    if light <= 0 or min(halves) < ALIGNED_MIN_SHARE * light:
        return math.nan
    p, t = pred[..., left].double(), target[..., left].double()
    den = float((p * p).sum())
    gain = float((p * t).sum()) / den if den > 0 else 1.0
    return psnr(pred[..., right] * gain, target[..., right], max_val)


def ssim(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0) -> float:
    """Mean SSIM (11x11 Gaussian window) of one image (C, H, W)."""
    return float(kornia.metrics.ssim(pred.clamp(0, max_val)[None], target[None], 11, max_val=max_val).mean())


#: the detail band's Gaussian sigma in pixels at 1/4 of ScalarFlow's native 1080x1920 frame
#: (270x480): structure finer than about 5 px there (20 native pixels) is "detail"
DETAIL_SIGMA_PX = 2.0
#: the shorter image side at which :data:`DETAIL_SIGMA_PX` applies; other sizes scale it
DETAIL_REFERENCE_PX = 270


def detail_band(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """The fine-detail band of images (..., C, H, W): each minus its Gaussian blur of ``sigma``
    pixels (kernel 2*ceil(3 sigma)+1, at most 2 min(H, W) - 1, reflected at the border)."""
    size = min(2 * math.ceil(3 * sigma) + 1, 2 * min(image.shape[-2:]) - 1)  # reflection needs pad < side
    H, W = image.shape[-2:]
    flat = image.detach().reshape(-1, H, W).double().cpu()
    kernel = kornia.filters.get_gaussian_kernel1d(size, sigma, dtype=torch.float64).numpy().ravel()
    # OpenCV's separable filter (reflect-101 = torch's reflect): kornia's blur on the CPU takes a
    # pass per kernel tap, 2-10x slower (a full-resolution ScalarFlow frame: 0.9 s against 0.4 s)
    blurred = torch.from_numpy(np.stack([
        cv2.sepFilter2D(plane, cv2.CV_64F, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)
        for plane in flat.numpy()]))
    return (flat - blurred).reshape(image.shape).to(image.device)


def detail_correlation(pred: torch.Tensor, target: torch.Tensor, sigma: float = DETAIL_SIGMA_PX,
                       mask: torch.Tensor | None = None) -> float:
    """How much of the capture's fine structure a render reproduces: the Pearson correlation of
    the fine-detail bands (:func:`detail_band`) of ``pred`` and ``target`` (C, H, W), over all
    channels of the pixels in ``mask`` (H, W) bool (default: the full frame). 1 is every wisp
    in place, 0 is a blur (or unrelated detail); NaN where either band is flat there. ``pred``
    is clipped to [0, 1] first, as for :func:`psnr`."""
    a, b = detail_band(pred.clamp(0, 1), sigma), detail_band(target, sigma)
    if mask is not None:
        a, b = a[:, mask], b[:, mask]
    a, b = a.reshape(-1), b.reshape(-1)
    if a.numel() < 2:
        return math.nan
    a, b = a - a.mean(), b - b.mean()
    den = float(a.norm() * b.norm())
    return float((a * b).sum()) / den if den > 0 else math.nan


def volume_errors(density: torch.Tensor, truth: torch.Tensor, support: float = 0.05) -> dict[str, float]:
    """Relative L2 error and support IoU of density (C, nz, ny, nx) against truth (same shape).

    The support is where the channel sum exceeds ``support`` times its maximum.
    """
    d, t = density.double(), truth.double()
    rel = float((d - t).norm() / t.norm().clamp_min(1e-300))
    ds, ts = d.sum(0), t.sum(0)
    a, b = ds > support * ds.max(), ts > support * ts.max()
    union = int((a | b).sum())
    iou = float((a & b).sum()) / union if union else 1.0
    return {"rel_l2": rel, "iou": iou}


def _cell_average_matrix(n_out: int, n_in: int) -> torch.Tensor:
    """(n_out, n_in) weights averaging n_in equal cells of [0, 1] into n_out equal cells:
    the length of each overlap divided by the output cell's length."""
    edges_in = torch.linspace(0, 1, n_in + 1, dtype=torch.float64)
    edges_out = torch.linspace(0, 1, n_out + 1, dtype=torch.float64)
    lo = torch.maximum(edges_out[:-1, None], edges_in[None, :-1])
    hi = torch.minimum(edges_out[1:, None], edges_in[None, 1:])
    return (hi - lo).clamp_min(0) * n_out


def resample_to(volume: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    """Exact cell averages of volume (C, nz, ny, nx) on another grid of the same box, (C, *shape)."""
    if tuple(volume.shape[1:]) == tuple(shape):
        return volume
    nz, ny, nx = volume.shape[1:]
    Wz, Wy, Wx = (_cell_average_matrix(o, i).to(volume.device) for o, i in zip(shape, (nz, ny, nx)))
    out = torch.einsum("cijk,dk->cijd", volume.double(), Wx)
    out = torch.einsum("cijd,bj->cibd", out, Wy)
    out = torch.einsum("cibd,ai->cabd", out, Wz)
    return out.to(volume.dtype)
