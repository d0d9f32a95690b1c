"""Pictures of a reconstruction: the paper's top view (Fig. 5), renders around the flame
(Fig. 6), orthogonal slices with a colour bar, turntable video/GIF, visual hull over images.

Images cross this module as ``(H, W, 3) uint8`` RGB arrays (what PNG, video and TensorBoard's
``dataformats="HWC"`` take); volumes as ``(C, nz, ny, nx)`` arrays or tensors, x fastest.
Only the slice figure needs matplotlib; everything else uses OpenCV, numpy and Pillow.
"""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from flamerecon.arguments import value, wrong_type, wrong_value
from flamerecon.geometry.axes import (
    UP_AXES,
    axis_index,
    axis_name,
    axis_sign,
    azimuth_zero,
    ground_directions,
)
from flamerecon.geometry.units import display_length
from flamerecon.outputs.atomic import atomic_path, atomic_write_bytes, write_errno
from flamerecon.outputs.export import voxel_size
from flamerecon.rules import number

_AXES = {"x": 2, "y": 1, "z": 0}  # world axis -> array axis of (nz, ny, nx)
_INSTALL_HINT = "install it with: pip install 'flamerecon[figures]'"


def to_display(image: torch.Tensor) -> torch.Tensor:
    """(C, H, W) image for display: grey images become RGB, values clipped to [0, 1]."""
    image = image.detach().float().cpu().clamp(0, 1)
    return image.expand(3, -1, -1) if image.shape[0] == 1 else image[:3]


#: heights and widths of the held-out figure's title strip and colour bar, pixels, for panels of
#: :data:`MIN_PANEL_PX` (:func:`figure_layout` scales them with the panels)
TITLE_PX, BAR_PX, BAR_LABEL_PX = 14, 8, 40
#: a held-out figure's panels are enlarged (by a whole factor, nearest neighbour) to at least this
#: height, so that a small capture's figure reads; its titles and labels grow with taller panels
MIN_PANEL_PX = 240


@dataclass(frozen=True)
class FigureLayout:
    """How a held-out figure of (H, W) images is drawn: ``scale``, the whole factor its panels
    are enlarged by; ``font`` (cv2's scale of its titles and labels), ``title_px`` (one title
    line's height), ``bar_px`` and ``bar_label_px`` (the colour bar's and its labels' widths),
    all in proportion to the enlarged panels' height (:data:`MIN_PANEL_PX` for the base sizes)."""

    scale: int
    font: float
    title_px: int
    bar_px: int
    bar_label_px: int


def figure_layout(height: int, width: int) -> FigureLayout:
    """The :class:`FigureLayout` of a held-out figure of ``height`` x ``width`` images."""
    scale = math.ceil(MIN_PANEL_PX / height) if height < MIN_PANEL_PX else 1
    size = height * scale / MIN_PANEL_PX if height * scale > MIN_PANEL_PX else 1.0
    return FigureLayout(scale, 0.35 * size, round(TITLE_PX * size), round(BAR_PX * size), round(BAR_LABEL_PX * size))


def heldout_figure(rendered: torch.Tensor, captured: torch.Tensor, view: str = "",
                   psnr: float | None = None, black: float | None = None,
                   sigma: torch.Tensor | None = None) -> np.ndarray:
    """A held-out view read without a legend: panels "rendered <view>" (with its ``psnr`` and
    the black image's, dB, when given) | "captured" | "|error|, image units" (| "predicted
    sigma" with ``sigma``, the render's confidence image (C, H, W):
    :mod:`flamerecon.evaluate.uncertainty`) under a title strip (two lines of it where a title
    is wider than its panel); the error and sigma (means over channels, in the images' units, 1
    = white) share the inferno colour map and its colour bar (0 at the bottom, the largest of
    them at the top) to their right. Sized by :func:`figure_layout`: panels of at least
    :data:`MIN_PANEL_PX` (a small capture enlarged), titles and labels in proportion: (strip +
    sH, n sW + bar + labels, 3) uint8 with n = 3 or 4 and s the layout's scale, from images
    (C, H, W) in [0, 1]."""
    r, c = to_display(rendered), to_display(captured)
    error = (rendered.detach().float().cpu().clamp(0, 1) - captured.detach().float().cpu()).abs().mean(0)
    spread = None if sigma is None else sigma.detach().float().cpu().mean(0)
    top = max(float(error.max()), 0.0 if spread is None else float(spread.max()))
    layout = figure_layout(*error.shape)
    k = layout.scale

    def big(panel: np.ndarray) -> np.ndarray:
        return panel if k == 1 else np.repeat(np.repeat(panel, k, 0), k, 1)

    H, W = error.shape[0] * k, error.shape[1] * k
    panels = [big((r.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)),
              big((c.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)), big(to_rgb8(error[None], top or 1.0))]
    ramp = np.linspace(top or 1.0, 0.0, H, dtype=np.float32)[:, None].repeat(layout.bar_px, 1)
    bar = np.zeros((H, layout.bar_px + layout.bar_label_px, 3), np.uint8)
    bar[:, :layout.bar_px] = to_rgb8(ramp[None], top or 1.0)
    scored = "" if psnr is None else f"{psnr:.2f} dB" + ("" if black is None else f" (black {black:.2f})")

    def fits(text: str) -> bool:
        return _text_width(text, layout.font) <= W - 4

    titles = [[f"rendered {view}".strip() + (f": {scored}" if scored else "")], ["captured"],
              ["|error|, image units" if fits("|error|, image units") else "|error|"]]
    if scored and not fits(titles[0][0]):  # a narrow panel: the scores on a second line
        titles[0] = [f"rendered {view}".strip(), scored]
    if spread is not None:
        panels.append(big(to_rgb8(spread[None], top or 1.0)))
        titles.append(["predicted sigma" if fits("predicted sigma") else "sigma"])
    n = len(panels)
    line = layout.title_px
    strip = line * max(len(t) for t in titles)
    figure = np.zeros((strip + H, n * W + bar.shape[1], 3), np.uint8)
    figure[strip:] = np.concatenate([*panels, bar], axis=1)
    thick = max(1, round(layout.font / 0.7))
    for j, lines in enumerate(titles):
        for row, title in enumerate(lines):
            cv2.putText(figure, title, (j * W + 2, (row + 1) * line - round(line * 0.3)), cv2.FONT_HERSHEY_SIMPLEX,
                        layout.font, (255, 255, 255), thick, cv2.LINE_AA)
    label = layout.font * 0.3 / 0.35
    for y, text in ((strip + round(line * 0.65), f"{top:.2g}"), (strip + H - 2, "0")):
        cv2.putText(figure, text, (n * W + layout.bar_px + 2, y), cv2.FONT_HERSHEY_SIMPLEX, label,
                    (255, 255, 255), thick, cv2.LINE_AA)
    return figure


def _text_width(text: str, font: float = 0.35) -> int:
    """Pixels a figure title takes (cv2's small font at ``font``)."""
    return cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font, 1)[0][0]


def detail_comparison(images: Sequence[torch.Tensor], bands: Sequence[torch.Tensor],
                      titles: Sequence[str]) -> np.ndarray:
    """One view's images (C, H, W) in [0, 1] side by side (the capture first, then renders),
    each titled, and under each its fine-detail band (H, W) (what the detail correlation
    compares, :func:`~flamerecon.evaluate.metrics.detail_band`): grey is none, white and black
    the first band's 99th percentile of |value| and beyond. (2 (TITLE_PX + H), len(images) W, 3)
    uint8."""
    if not len(images) == len(bands) == len(titles) or not images:
        raise ValueError(f"detail_comparison: {len(images)} images, {len(bands)} bands, {len(titles)} titles")
    scale = float(torch.quantile(bands[0].detach().float().cpu().abs().flatten(), 0.99)) or 1.0
    H, W = images[0].shape[-2:]
    rows = []
    for row_titles, panels in (
        (titles, [(to_display(img).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8) for img in images]),
        (["detail band"] + [""] * (len(bands) - 1),
         [np.repeat(((band.detach().float().cpu() / scale).clamp(-1, 1).numpy() * 127.5 + 127.5
                     ).astype(np.uint8)[..., None], 3, -1) for band in bands])):
        row = np.zeros((TITLE_PX + H, len(images) * W, 3), np.uint8)
        row[TITLE_PX:] = np.concatenate(panels, axis=1)
        for n, title in enumerate(row_titles):
            cv2.putText(row, title, (n * W + 2, TITLE_PX - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                        (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    return np.concatenate(rows, axis=0)


def _numpy(value) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().float().cpu().numpy()
    return np.asarray(value, dtype=np.float32)


def to_rgb8(image, vmax: float | None = None, colormap: int = cv2.COLORMAP_INFERNO) -> np.ndarray:
    """Image (C, H, W) -> (H, W, 3) uint8 RGB, values scaled by ``vmax`` (default: image max).

    Three channels are shown as colour; one channel (or any other count, summed) through
    ``colormap``. Negative values clip to 0.
    """
    img = _numpy(image)
    if img.ndim == 2:
        img = img[None]
    if img.ndim != 3:
        raise ValueError(f"to_rgb8: image must be (C, H, W), got shape {img.shape}")
    if img.shape[0] != 3:
        img = img.sum(axis=0, keepdims=True)
    top = float(img.max()) if vmax is None else float(vmax)
    scaled = np.clip(img / top, 0.0, 1.0) if top > 0 else np.zeros_like(img)
    as8 = np.round(scaled * 255).astype(np.uint8)
    if as8.shape[0] == 3:
        return np.ascontiguousarray(as8.transpose(1, 2, 0))
    bgr = cv2.applyColorMap(as8[0], colormap)
    return np.ascontiguousarray(bgr[..., ::-1])


def project_along(density, bbox_min, bbox_max, axis: str = "y") -> np.ndarray:
    """Orthographic line integral of the density along world ``axis`` (``x``, ``y``, ``z``, or
    a signed name such as ``-z``: the same integral), the emission seen from far along that
    axis (world units): (C, nz, ny, nx) -> (C, rows, cols).

    Remaining axes in array order: along y -> (C, nz, nx), along z -> (C, ny, nx),
    along x -> (C, nz, ny); rows grow downwards in the image.
    """
    vol = _numpy(density)
    name = axis_name(axis)
    if name is None:
        raise ValueError(f"project_along: axis must be one of x, y, z (or {', '.join(UP_AXES)}), got {axis!r}")
    step = voxel_size(bbox_min, bbox_max, vol.shape)[axis_index(name)]
    return vol.sum(axis=1 + _AXES[name[-1]]) * np.float32(step)


def _up(up: str) -> str:
    name = axis_name(up)
    if name is None:
        raise ValueError(f"up: must be one of {', '.join(UP_AXES)}, got {up!r}")
    return name


def _array_axes(fixed: int) -> tuple[int, int]:
    """The world axes (indices) of a volume's array dimensions left when world axis ``fixed`` is
    summed or cut, in array order (z, y, x)."""
    return tuple(a for a in (2, 1, 0) if a != fixed)


def oriented(plane: np.ndarray, axes: tuple[int, int], rows: tuple[int, float], cols: tuple[int, float]) -> np.ndarray:
    """A (..., A, B) array whose last two dimensions run along world axes ``axes`` (array order),
    arranged so that its rows run along the signed world direction ``rows`` and its columns
    along ``cols`` ((axis index, +-1.0) each, :func:`~flamerecon.geometry.axes.ground_directions`)."""
    out = plane if tuple(axes) == (rows[0], cols[0]) else np.swapaxes(plane, -1, -2)
    if rows[1] < 0:
        out = np.flip(out, -2)
    if cols[1] < 0:
        out = np.flip(out, -1)
    return np.ascontiguousarray(out)


def _span(lo: np.ndarray, hi: np.ndarray, direction: tuple[int, float]) -> tuple[float, float]:
    """The world coordinates a figure's axis runs through along the signed ``direction``."""
    a, sign = direction
    return (lo[a], hi[a]) if sign > 0 else (hi[a], lo[a])


def top_view(density, bbox_min, bbox_max, up: str = "+y", vmax: float | None = None) -> np.ndarray:
    """The paper's Fig. 5: the density seen from above (along the ``up`` axis, e.g. ``+z``) as
    (H, W, 3) uint8, oriented by :func:`~flamerecon.geometry.axes.ground_directions` (a scene
    turned to another up shows the same picture); log it every N iterations to watch the solve
    sharpen."""
    up = _up(up)
    across, depth = ground_directions(up)
    seen = project_along(density, bbox_min, bbox_max, up)
    return to_rgb8(oriented(seen, _array_axes(axis_index(up)), depth, across), vmax)


def top_view_figure(path: str | os.PathLike, density, bbox_min, bbox_max, up: str = "+y", title: str = "",
                    unit: float | None = None) -> Path:
    """PNG of the paper's Fig. 5 read alone: the density seen from above (its line integral along
    the ``up`` axis, channels summed: what a camera far above would record, in image units) on
    axes in the scene's length ``unit`` (metres per world unit; None: world units), with its
    colour bar and a title."""
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError(f"top_view.png needs matplotlib; {_INSTALL_HINT}") from err
    up = _up(up)
    across, depth = ground_directions(up)
    depth = (depth[0], -depth[1])  # upwards in the figure: seen from above, not mirrored from below
    seen = oriented(project_along(density, bbox_min, bbox_max, up).sum(axis=0), _array_axes(axis_index(up)),
                    depth, across)
    factor, length = display_length(unit, float(np.max(np.subtract(bbox_max, bbox_min))))
    lo, hi = np.asarray(bbox_min, float) * factor, np.asarray(bbox_max, float) * factor
    fig = Figure(figsize=(5.2, 4.4), dpi=100, layout="constrained")
    ax = fig.subplots()
    shown = ax.imshow(seen, origin="lower", extent=(*_span(lo, hi, across), *_span(lo, hi, depth)),
                      cmap="inferno", vmin=0.0, interpolation="nearest")
    ax.set_xlabel(f"{'xyz'[across[0]]} ({length})")
    ax.set_ylabel(f"{'xyz'[depth[0]]} ({length})")
    fig.colorbar(shown, ax=ax, label=f"emission integrated along {up[-1]} (image units)")
    ax.set_title(f"{title + chr(10) if title else ''}density seen from above, along {up} (the paper's Fig. 5)",
                 fontsize="medium")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def centroid_index(density) -> tuple[int, int, int]:
    """The voxel (i, j, k) nearest the density's centre of mass (channels summed; the grid's
    centre for an empty volume)."""
    total = _numpy(density).sum(axis=0)
    mass = float(total.sum())
    if mass <= 0:
        nz, ny, nx = total.shape
        return nx // 2, ny // 2, nz // 2
    k, j, i = (float((total.sum(axis=tuple(a for a in range(3) if a != ax)) * np.arange(n)).sum()) / mass
               for ax, n in enumerate(total.shape))
    return round(i), round(j), round(k)


def brightest_index(density) -> tuple[int, int, int]:
    """The voxel (i, j, k) at the middle of the brightest region of the density (channels
    summed, averaged over cubes of about a sixteenth of the grid's longest side, at least 3
    voxels): where slices cut through smoke even when the centre of mass falls between two
    lobes. The grid's centre for an empty volume."""
    total = torch.from_numpy(np.ascontiguousarray(_numpy(density).sum(axis=0)))
    if float(total.max()) <= 0:
        nz, ny, nx = total.shape
        return nx // 2, ny // 2, nz // 2
    width = max(3, round(max(total.shape) / 16)) | 1  # odd: centred
    box = torch.ones(1, 1, width, width, width, dtype=total.dtype)
    sums = torch.nn.functional.conv3d(total[None, None], box, padding=width // 2)[0, 0]
    counts = torch.nn.functional.conv3d(torch.ones_like(total)[None, None], box, padding=width // 2)[0, 0]
    smooth = sums / counts  # the mean over the cube's voxels inside the grid
    k, j, i = np.unravel_index(int(smooth.argmax()), tuple(total.shape))
    return int(i), int(j), int(k)


def slice_panels(scalar: np.ndarray, lo: np.ndarray, hi: np.ndarray, index: Sequence[int], up: str = "+y"
                 ) -> list[tuple[np.ndarray, tuple[int, float], tuple[int, float], str]]:
    """The three planes of a (nz, ny, nx) ``scalar`` through voxel ``index`` = (i, j, k), as
    (image rows x cols with row 0 at the bottom, horizontal direction, vertical direction,
    title), the directions signed world axes (axis index, +-1.0): the two vertical planes with
    ``up`` upward, then the horizontal one seen from above, oriented as
    :func:`~flamerecon.geometry.axes.ground_directions` says."""
    up = _up(up)
    rise = (axis_index(up), axis_sign(up))
    across, depth = ground_directions(up)
    above = (depth[0], -depth[1])  # the horizontal plane's upwards direction, seen from above
    centre = lo + (np.asarray(index) + 0.5) * voxel_size(lo, hi, scalar.shape)

    def plane(h: tuple[int, float], v: tuple[int, float]) -> tuple[np.ndarray, str]:
        fixed = 3 - h[0] - v[0]
        cut = np.take(scalar, int(index[fixed]), axis=_AXES["xyz"[fixed]])
        name = f"{'xyz'[h[0]]}{'xyz'[v[0]]} plane at {'xyz'[fixed]} = {centre[fixed]:.3g}"
        return oriented(cut, _array_axes(fixed), v, h), name

    out = []
    for h, v in ((across, rise), (depth, rise), (across, above)):
        picture, name = plane(h, v)
        out.append((picture, h, v, name))
    return out


def slices_figure(
    path: str | os.PathLike,
    density,
    bbox_min,
    bbox_max,
    index: Sequence[int] | None = None,
    channel: int | None = None,
    title: str = "",
    up: str = "+y",
    unit: float | None = None,
) -> Path:
    """PNG of three planes through voxel ``index`` = (i, j, k) (default: the middle of the
    brightest region, :func:`brightest_index`), the two vertical ones with world axis ``up``
    upward (:func:`slice_panels`), axes in the scene's length ``unit`` (metres per world unit;
    None: world units), one shared colour bar. ``channel`` picks one colour channel; default:
    their sum (total emission)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as err:
        raise ImportError(f"slices_figure needs matplotlib; {_INSTALL_HINT}") from err
    vol = _numpy(density)
    scalar = vol.sum(axis=0) if channel is None else vol[channel]
    nz, ny, nx = scalar.shape
    i, j, k = brightest_index(scalar[None]) if index is None else (int(v) for v in index)
    if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
        raise ValueError(f"slices_figure: index {(i, j, k)} outside the grid (nx, ny, nz) = "
                         f"{(nx, ny, nz)}")
    factor, length = display_length(unit, float(np.max(np.subtract(bbox_max, bbox_min))))
    lo, hi = np.asarray(bbox_min, float) * factor, np.asarray(bbox_max, float) * factor
    panels = slice_panels(scalar, lo, hi, (i, j, k), up)
    vmax = max(float(p[0].max()) for p in panels) or 1.0
    fig = Figure(figsize=(13, 4.2), dpi=100, layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, (plane, h, v, label) in zip(axes, panels):
        shown = ax.imshow(plane, origin="lower", extent=(*_span(lo, hi, h), *_span(lo, hi, v)),
                          cmap="inferno", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_xlabel(f"{'xyz'[h[0]]} ({length})")
        ax.set_ylabel(f"{'xyz'[v[0]]} ({length})")
        ax.set_title(label)
    fig.colorbar(shown, ax=list(axes), shrink=0.9,
                 label=("density" if channel is None else f"density, channel {channel}")
                 + " (image units per world unit)")
    where = "the middle of its brightest region, voxel" if index is None else "voxel"
    fig.suptitle(f"{title + ': ' if title else ''}density through {where} {(i, j, k)}")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def overlay_mask(image, mask, color: tuple[int, int, int] = (0, 255, 0),
                 alpha: float = 0.3) -> np.ndarray:
    """A silhouette (e.g. the visual hull projected into a view) over an image.

    image: (C, H, W) float in [0, 1] or (H, W, 3) uint8; mask: (H, W) bool. The mask is tinted
    with ``color`` at ``alpha`` and its outline drawn at full strength. Returns (H, W, 3) uint8.
    """
    if isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3:
        rgb = image.copy()
    else:
        rgb = to_rgb8(image, vmax=1.0)
    region = _numpy(mask).astype(bool)
    if region.shape != rgb.shape[:2]:
        raise ValueError(f"overlay_mask: mask {region.shape} and image {rgb.shape[:2]} differ")
    tint = np.array(color, dtype=np.float32)
    rgb[region] = np.round((1 - alpha) * rgb[region] + alpha * tint).astype(np.uint8)
    contours, _ = cv2.findContours(region.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(rgb, contours, -1, tuple(int(c) for c in color), 1)
    return rgb


def montage(images: Sequence[np.ndarray], columns: int, labels: Sequence[str] = ()) -> np.ndarray:
    """Tile (H, W, 3) uint8 images row by row (black where a row runs short), optional labels
    drawn in the top-left corner of each tile."""
    if not images:
        raise ValueError("montage: no images")
    h, w = images[0].shape[:2]
    rows = math.ceil(len(images) / columns)
    sheet = np.zeros((rows * h, columns * w, 3), dtype=np.uint8)
    for n, img in enumerate(images):
        if img.shape != (h, w, 3):
            raise ValueError(f"montage: image {n} is {img.shape}, expected {(h, w, 3)}")
        r, c = divmod(n, columns)
        tile = np.ascontiguousarray(img)
        if n < len(labels):
            cv2.putText(tile, str(labels[n]), (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        (255, 255, 255), 1, cv2.LINE_AA)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return sheet


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """(H, W, 3) uint8 RGB to PNG, atomically. Encoded in memory: ``cv2.imwrite`` reports
    success for a file it could not finish (a full disk), Python's own write does not."""
    path = Path(path)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode a {image.shape} {image.dtype} image as PNG")
    return atomic_write_bytes(path, png.tobytes())


def write_mp4(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = 24.0) -> Path:
    """Frames (H, W, 3) uint8 RGB to an MPEG-4 (``mp4v``) video through OpenCV, atomically.

    ``mp4v`` is the codec opencv-python-headless ships an encoder for (no H.264); VLC, ffmpeg
    and most players open it, some web browsers do not: use the GIF there."""
    frames = _check_frames(frames, "write_mp4")
    h, w = frames[0].shape[:2]
    path = Path(path)
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV has no mp4v encoder here")
        try:
            for frame in frames:
                writer.write(np.ascontiguousarray(frame[..., ::-1]))
        finally:
            writer.release()
        _check_video(tmp, path, len(frames))
    return path


def _check_video(tmp: Path, path: Path, count: int) -> None:
    """Read the video OpenCV wrote at ``tmp`` back: its writer reports no failed write (a full
    disk leaves a file without its index), so a file that does not open with ``count`` frames
    is an error naming ``path``."""
    video = cv2.VideoCapture(str(tmp)) if tmp.stat().st_size else None
    frames = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video is not None and video.isOpened() else 0
    if video is not None:
        video.release()
    if frames != count:
        raise write_errno(tmp.parent, OSError(f"the video has {frames} of {count} frames"))


def write_gif(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = 12.0) -> Path:
    """Frames (H, W, 3) uint8 RGB to a looping GIF through Pillow, atomically."""
    try:
        from PIL import Image
    except ImportError as err:
        raise ImportError(f"write_gif needs Pillow; {_INSTALL_HINT}") from err
    frames = _check_frames(frames, "write_gif")
    pictures = [Image.fromarray(f) for f in frames]
    path = Path(path)
    with atomic_path(path) as tmp:
        pictures[0].save(tmp, format="GIF", save_all=True, append_images=pictures[1:],
                         duration=max(20, round(1000 / fps)), loop=0)
    return path


def _check_frames(frames: Sequence[np.ndarray], who: str) -> list[np.ndarray]:
    frames = list(frames)
    if not frames:
        raise ValueError(f"{who}: no frames")
    shape = frames[0].shape
    for n, f in enumerate(frames):
        if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3 or f.shape != shape:
            raise ValueError(f"{who}: frame {n} must be (H, W, 3) uint8 like frame 0 {shape}, "
                             f"got {f.dtype} {f.shape}")
    return frames


def orbit_cameras(
    azimuth_deg: Sequence[float] | float,
    elevation_deg: float,
    distance: float,
    target: Sequence[float],
    width: int = 320,
    height: int = 240,
    fov_deg: float = 40.0,
    up: Sequence[float] = (0.0, 1.0, 0.0),
):
    """Cameras on a circle around ``target`` looking at it (kornia batch, one per azimuth).

    Azimuth turns about the ``up`` direction, 0 on the side of :func:`azimuth_zero` (+z for up
    = +y; for up along an axis, +y's +z turned as :func:`~flamerecon.geometry.axes.turn_from_y`
    turns +y onto it, so a turned scene's orbits are the same) and 90 a right angle on about up
    (+x for up = +y);
    elevation lifts the camera towards ``up``; distance in world units; ``fov_deg`` the
    vertical field of view. Pixel centres at +0.5 (flamerecon's convention).
    """
    from flamerecon.geometry.cameras import look_at_camera, points

    azimuths = _angles("orbit_cameras.azimuth_deg", azimuth_deg)
    value("orbit_cameras.elevation_deg", elevation_deg, number(-90.0, 90.0))
    value("orbit_cameras.distance", distance, number(0.0, lo_open=True))
    target = points("orbit_cameras.target", target, 1)[0].numpy()
    up = points("orbit_cameras.up", up, 1)[0].numpy()
    if not np.linalg.norm(up):
        raise wrong_value("orbit_cameras.up", up, "a non-zero direction")
    up_dir = np.asarray(up, dtype=np.float64)
    up_dir = up_dir / np.linalg.norm(up_dir)
    first = azimuth_zero(up_dir)
    first = first - (first @ up_dir) * up_dir
    first /= np.linalg.norm(first)
    second = np.cross(up_dir, first)  # +x for up = +y, first = +z
    az = np.radians(azimuths)
    el = math.radians(float(elevation_deg))
    offsets = distance * (math.cos(el) * (np.cos(az)[:, None] * first + np.sin(az)[:, None] * second)
                          + math.sin(el) * up_dir)
    centre = np.asarray(target, dtype=np.float64)
    eyes = centre + offsets
    return look_at_camera(torch.from_numpy(eyes), torch.from_numpy(centre).expand(len(az), 3),
                          torch.from_numpy(up_dir), width, height, fov_deg)


def _angles(name: str, given) -> np.ndarray:
    """``given`` (a number or a non-empty flat sequence, array or tensor of finite numbers) as a
    float64 array."""
    flat = given.tolist() if isinstance(given, (np.ndarray, torch.Tensor)) else given
    items = list(flat) if isinstance(flat, Sequence) and not isinstance(flat, str) else [flat]
    want = "an angle in degrees or a non-empty list of them"
    if any(isinstance(a, bool) or not isinstance(a, numbers.Real) for a in items):
        raise wrong_type(name, given, want)
    if not items:
        raise wrong_value(name, given, want)
    for a in items:
        value(name, a, number())
    return np.asarray(items, dtype=np.float64)


def framing_distance(bbox_min, bbox_max, fov_deg: float, margin: float = 1.1) -> float:
    """Distance from the box centre at which a camera with vertical field of view ``fov_deg``
    sees the whole box (its bounding sphere) with ``margin``."""
    radius = 0.5 * float(np.linalg.norm(np.asarray(bbox_max, float) - np.asarray(bbox_min, float)))
    return margin * radius / math.sin(math.radians(fov_deg) / 2)


def support_box(density, bbox_min, bbox_max, threshold: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """World box (min xyz, max xyz) of the voxels brighter than ``threshold`` times the
    brightest (channels summed), cell extents included; the whole box for an empty volume."""
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    total = _numpy(density).sum(axis=0)
    peak = float(total.max())
    if peak <= 0:
        return lo, hi
    k, j, i = np.nonzero(total > threshold * peak)
    size = voxel_size(lo, hi, total.shape)
    first = np.array([i.min(), j.min(), k.min()])
    last = np.array([i.max(), j.max(), k.max()]) + 1
    return lo + first * size, lo + last * size


# ---------------------------------------------------------------------------------------------
# renders of a density through the projector


def grid_of(density, bbox_min, bbox_max):
    """The VoxelGrid a (C, nz, ny, nx) density of ``density.npz`` lives on."""
    from flamerecon.geometry.grid import VoxelGrid

    nz, ny, nx = density.shape[-3:]
    return VoxelGrid.from_box(tuple(np.asarray(bbox_min, float)), tuple(np.asarray(bbox_max, float)),
                              (nx, ny, nz))


def render_views(density, bbox_min, bbox_max, cams, step: float = 0.5, device=None,
                 batch: int = 8) -> torch.Tensor:
    """Full images of the density from every camera of ``cams``: (B, C, H, W) float32 on the
    CPU, pixel = line integral in world units (the projector's matrix-free renderer), rendered
    ``batch`` cameras at a time on ``device`` (default: the density's, CPU for numpy)."""
    from flamerecon.geometry.cameras import camera_subset, cameras_to
    from flamerecon.operators.projector import render_image

    volume = density if isinstance(density, torch.Tensor) else torch.from_numpy(_numpy(density))
    if device is not None:
        volume = volume.to(device)
    volume = volume.float()
    grid = grid_of(volume, bbox_min, bbox_max)
    cams = cameras_to(cams, volume.device)
    out = []
    for start in range(0, cams.batch_size, batch):
        index = list(range(start, min(start + batch, cams.batch_size)))
        out.append(render_image(volume, grid, camera_subset(cams, index), step=step).cpu())
    return torch.cat(out)


def views_around(density, bbox_min, bbox_max, n: int = 10, elevation_deg: float = 15.0,
                 width: int = 320, height: int = 240, fov_deg: float = 40.0,
                 up: Sequence[float] = (0.0, 1.0, 0.0), columns: int = 5, device=None,
                 vmax: float | None = None) -> np.ndarray:
    """The paper's Fig. 6: the density rendered from ``n`` views evenly around it, one
    brightness scale for all (``vmax``, default the brightest pixel), tiled ``columns`` wide
    and labelled with the azimuth: (rows * height, columns * width, 3) uint8. The cameras
    frame the flame (voxels above 1 % of the peak) and look at its centre."""
    azimuths = np.arange(n) * 360.0 / n
    images = _orbit_renders(density, bbox_min, bbox_max, azimuths, elevation_deg, width, height,
                            fov_deg, up, device, vmax)
    return montage(images, columns, labels=[f"{a:.0f} deg" for a in azimuths])


def turntable_frames(density, bbox_min, bbox_max, n_frames: int = 36,
                     elevation_deg: float = 15.0, width: int = 320, height: int = 240,
                     fov_deg: float = 40.0, up: Sequence[float] = (0.0, 1.0, 0.0),
                     device=None, vmax: float | None = None) -> list[np.ndarray]:
    """``n_frames`` renders on a full circle, one brightness scale (``vmax``, default the
    brightest pixel): frames for :func:`write_mp4` / :func:`write_gif`."""
    azimuths = np.arange(n_frames) * 360.0 / n_frames
    return _orbit_renders(density, bbox_min, bbox_max, azimuths, elevation_deg, width, height,
                          fov_deg, up, device, vmax)


def hull_masks(hull, grid, cams) -> torch.Tensor:
    """Where the visual hull (nz, ny, nx) bool on ``grid`` projects in every camera:
    (B, H, W) bool, by rendering its indicator (nonzero line integral)."""
    from flamerecon.operators.projector import render_image

    indicator = torch.as_tensor(hull, device=cams.intrinsics.device).float()[None]
    return render_image(indicator, grid, cams)[:, 0].cpu() > 0


def _orbit_renders(density, bbox_min, bbox_max, azimuths, elevation_deg, width, height, fov_deg,
                   up, device, vmax) -> list[np.ndarray]:
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    near, far = support_box(density, lo, hi)
    cams = orbit_cameras(azimuths, elevation_deg, framing_distance(near, far, fov_deg),
                         (near + far) / 2, width, height, fov_deg, up)
    images = render_views(density, lo, hi, cams, device=device)
    vmax = float(images.max()) if vmax is None else vmax
    return [to_rgb8(img, vmax) for img in images]
