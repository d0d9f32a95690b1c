"""Camera photometry: from recorded pixel values to values linear in emitted radiance, and the
per-camera gain and offset that tie a rendered line integral to what a camera recorded.

The image model is ``image = gain * integral + offset`` per camera (``cameras.json`` stores
``gain`` and ``offset``); :func:`linearize` undoes the sensor's response curve first.
"""

from __future__ import annotations

import torch


def srgb_to_linear(values: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer curve inverted (IEC 61966-2-1), elementwise on values in [0, 1]."""
    v = values.clamp(0.0, 1.0)
    return torch.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(values: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer curve (IEC 61966-2-1), elementwise on linear values >= 0."""
    v = values.clamp_min(0.0)
    return torch.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def linearize(
    images: torch.Tensor, gamma: float | str = 1.0, black_level: float = 0.0
) -> torch.Tensor:
    """Recorded images (B, C, H, W) in [0, 1] -> values linear in radiance, in [0, 1].

    ``black_level`` (in recorded units) is subtracted and the rest stretched back to [0, 1];
    then the response is undone: ``value ** gamma`` for a number (1 = already linear, 2.2 for
    a typical video curve) or the sRGB curve for ``gamma="srgb"``.
    """
    if not 0.0 <= float(black_level) < 1.0:
        raise ValueError(f"scene.black_level: must be in [0, 1), got {black_level}")
    out = images
    if black_level:
        out = ((out - black_level) / (1.0 - black_level)).clamp_min(0.0)
    if isinstance(gamma, str):
        if gamma.lower() != "srgb":
            raise ValueError(f"scene.gamma: a positive number or 'srgb', got '{gamma}'")
        return srgb_to_linear(out)
    if float(gamma) <= 0:
        raise ValueError(f"scene.gamma: must be positive, got {gamma}")
    if float(gamma) != 1.0:
        out = out.clamp_min(0.0) ** float(gamma)
    return out


def delinearize(
    values: torch.Tensor, gamma: float | str = 1.0, black_level: float = 0.0
) -> torch.Tensor:
    """The inverse of :func:`linearize`: linear values (>= 0, may exceed 1) -> recorded units,
    so a render can be scored against what the camera recorded. The identity for gamma 1 and
    black level 0; exact on recorded values at or above the black level."""
    if isinstance(gamma, str):
        out = linear_to_srgb(values)
    elif float(gamma) != 1.0:
        out = values.clamp_min(0.0) ** (1.0 / float(gamma))
    else:
        out = values
    if black_level:
        out = black_level + (1.0 - black_level) * out
    return out


def fit_gain_offset(
    rendered: torch.Tensor,
    captured: torch.Tensor,
    mask: torch.Tensor | None = None,
    fit_offset: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera least-squares ``captured ~ gain * rendered + offset``.

    ``rendered`` and ``captured``: (B, C, H, W) (or (B, N) flattened pixels); ``mask``
    (B, H, W) bool (or (B, N)) selects the pixels that count, e.g. the silhouettes. Returns
    ``gain`` (B,) and ``offset`` (B,) (zeros when ``fit_offset`` is False). A camera whose
    rendering is constant over its pixels keeps gain 1.
    """
    B = rendered.shape[0]
    r = rendered.double().reshape(B, -1)
    c = captured.double().reshape(B, -1)
    if mask is None:
        w = torch.ones_like(r)
    else:
        m = mask.to(r.dtype)
        if rendered.dim() == 4:  # one mask per view, shared by its channels
            m = m[:, None].expand(rendered.shape)
        w = m.reshape(B, -1)
    n = w.sum(1).clamp_min(1.0)
    if fit_offset:
        mr, mc = (w * r).sum(1) / n, (w * c).sum(1) / n
        var = (w * (r - mr[:, None]) ** 2).sum(1)
        cov = (w * (r - mr[:, None]) * (c - mc[:, None])).sum(1)
        gain = torch.where(var > 1e-20, cov / var.clamp_min(1e-20), torch.ones_like(var))
        offset = mc - gain * mr
    else:
        rr = (w * r * r).sum(1)
        gain = torch.where(
            rr > 1e-20, (w * r * c).sum(1) / rr.clamp_min(1e-20), torch.ones_like(rr)
        )
        offset = torch.zeros_like(gain)
    return gain.to(rendered.dtype), offset.to(rendered.dtype)


def apply_gain_offset(
    images: torch.Tensor, gain: torch.Tensor, offset: torch.Tensor
) -> torch.Tensor:
    """``gain * images + offset`` per camera: images (B, ...), gain and offset (B,)."""
    shape = (-1,) + (1,) * (images.dim() - 1)
    return images * gain.reshape(shape) + offset.reshape(shape)


def remove_gain_offset(
    images: torch.Tensor, gain: torch.Tensor, offset: torch.Tensor
) -> torch.Tensor:
    """Inverse of :func:`apply_gain_offset`: the line integrals a camera's images imply."""
    shape = (-1,) + (1,) * (images.dim() - 1)
    return (images - offset.reshape(shape)) / gain.reshape(shape)


def fit_gain_offset_rows(
    predicted: torch.Tensor,
    captured: torch.Tensor,
    view: torch.Tensor,
    num_views: int,
    fit_offset: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`fit_gain_offset` for stacked pixel rows, as the solver sees them.

    ``predicted`` and ``captured``: (N, C) values of the rows (e.g. ``A x`` and the data);
    ``view`` (N,) long: which camera each row belongs to. Returns gain and offset (num_views,);
    a camera with no rows, or a constant prediction, keeps gain 1 and offset 0.
    """
    r = predicted.double().reshape(predicted.shape[0], -1)
    c = captured.double().reshape(captured.shape[0], -1)
    idx = view.long()

    def per_view(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros(num_views, dtype=torch.float64, device=r.device).index_add_(
            0, idx, values.sum(1)
        )

    n = per_view(torch.ones_like(r))
    sr, sc, srr, src = per_view(r), per_view(c), per_view(r * r), per_view(r * c)
    if fit_offset:
        var = srr - sr * sr / n.clamp_min(1.0)
        cov = src - sr * sc / n.clamp_min(1.0)
        ok = (n > 1) & (var > 1e-20)
        gain = torch.where(ok, cov / var.clamp_min(1e-20), torch.ones_like(var))
        offset = torch.where(ok, (sc - gain * sr) / n.clamp_min(1.0), torch.zeros_like(var))
    else:
        ok = srr > 1e-20
        gain = torch.where(ok, src / srr.clamp_min(1e-20), torch.ones_like(srr))
        offset = torch.zeros_like(gain)
    return gain.to(predicted.dtype), offset.to(predicted.dtype)


def normalize_gains(gain: torch.Tensor) -> torch.Tensor:
    """Gains (B,) divided by their geometric mean.

    Density and gains trade a common factor (``g * integral`` is unchanged by ``g / a`` and
    ``a * density``); fixing the geometric mean at 1 lets a camera with no fitted gain (a
    held-out view) use gain 1 and offset 0. Offsets are unaffected.
    """
    return gain / torch.exp(torch.log(gain.clamp_min(1e-12)).mean())
