"""Silhouettes: which pixels see the flame."""

from __future__ import annotations

import cv2
import numpy as np
import torch


def silhouettes(
    images: torch.Tensor, method: str = "threshold", threshold: float = 0.03,
    dilate_px: int = 2, open_px: int = 1, background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Binary silhouettes (B, H, W) of images (B, C, H, W) in [0, 1].

    ``threshold``: a pixel is flame where its brightest channel (minus ``background`` when
    given) exceeds it. ``open_px`` removes specks of noise, ``dilate_px`` grows the result
    as a safety margin so that faint edges are not carved away.
    """
    if method != "threshold":
        raise ValueError(f"silhouette.method: unknown method '{method}'; use 'threshold'")
    signal = images if background is None else images - background
    masks = (signal.amax(1) > threshold).cpu().numpy().astype(np.uint8)
    out = []
    for m in masks:
        if open_px > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * open_px + 1, 2 * open_px + 1))
            m = cv2.morphologyEx(m, cv2.MORPH_OPEN, k)
        if dilate_px > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
            m = cv2.dilate(m, k)
        out.append(torch.from_numpy(m.astype(bool)))
    return torch.stack(out).to(images.device)
