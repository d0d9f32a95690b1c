"""Published evaluation protocols: a density scored the way a paper scores its own results, so
that a table can sit beside the paper's.

``hyfluid`` (HyFluid, Yu et al. 2023, on ScalarFlow): cameras 0, 1, 3 and 4 fitted, camera 2
(``train02``) scored at half the capture's resolution (540 x 960), on rows 90-960 and columns
45-540 of each frame (the plume, without the empty top rows and the left margin), PSNR on [0, 1]
and SSIM as scikit-image computes it (``structural_similarity`` with ``data_range=1``: a 7x7
uniform window). Whatever resolution the density was reconstructed at, it is rendered into
that camera at that resolution.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from flamerecon.errors import ConfigError
from flamerecon.evaluate.metrics import detail_correlation, psnr
from flamerecon.evaluate.scores import detail_sigma
from flamerecon.geometry.cameras import camera_subset, cameras_to, resized_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.scenes import Scene, load_scene


@dataclass(frozen=True)
class Protocol:
    """Which view is scored, at which ``downscale`` of the capture, on which crop (rows and
    columns, [first, end) in pixels of those images; None: all), and the views fitted."""

    name: str
    view: str
    downscale: int
    rows: tuple[int, int] | None
    cols: tuple[int, int] | None
    train: tuple[str, ...]


SCALARFLOW_TRAIN = ("train00", "train01", "train03", "train04")
PROTOCOLS = {"hyfluid": Protocol("hyfluid", "train02", 2, (90, 960), (45, 540), SCALARFLOW_TRAIN),
             # the same view and resolution, full frame: the ladder's runs compared at one resolution
             "half": Protocol("half", "train02", 2, None, None, SCALARFLOW_TRAIN)}


def structural_similarity(image: torch.Tensor, reference: torch.Tensor) -> float:
    """SSIM of two images (C, H, W) in [0, 1] as scikit-image computes it (``data_range=1``,
    its default 7x7 uniform window, channels averaged)."""
    try:
        from skimage.metrics import structural_similarity as skimage_ssim
    except ImportError as err:
        raise ConfigError("protocol: SSIM as the paper computes it needs scikit-image; "
                          "pip install 'flamerecon[export]'") from err
    a, b = (t.detach().cpu().double().numpy() for t in (image, reference))
    if a.shape[0] == 1:
        return float(skimage_ssim(a[0], b[0], data_range=1.0))
    return float(skimage_ssim(a, b, data_range=1.0, channel_axis=0))


def protocol_scores(protocol: Protocol, scene_options: Mapping, scene: Scene, train: list[int],
                    volume: torch.Tensor, grid: VoxelGrid, step: float = 0.5) -> dict[str, float]:
    """``psnr``, ``ssim``, ``detail`` and ``psnr_black`` of a density (C, nz, ny, nx) on
    ``grid`` under ``protocol``: the frame of ``scene_options`` (a ``scene:`` node) loaded at the
    protocol's downscale, the density rendered into its view through ``scene``'s camera of that
    view (the run's: a rig calibration's refined one too) resized to those images, both cropped.
    ``train``: the run's training views of ``scene``, which must be the protocol's."""
    fitted = tuple(scene.views[v] for v in train)
    if sorted(fitted) != sorted(protocol.train):
        raise ConfigError(f"protocol {protocol.name}: it fits {list(protocol.train)} and scores {protocol.view}, "
                          f"but the run fitted {list(fitted)}; run with holdout=[{protocol.view}]")
    if protocol.view not in scene.views:
        raise ConfigError(f"protocol {protocol.name}: the scene has no view {protocol.view!r} (views {scene.views})")
    at = load_scene({**scene_options, "downscale": protocol.downscale})
    v = at.views.index(protocol.view)
    camera = resized_cameras(camera_subset(scene.cameras, [scene.views.index(protocol.view)]), *at.image_size)
    rendered = render_image(volume, grid, cameras_to(camera, volume.device), step)[0].cpu()
    rows, cols = (slice(*span) if span else slice(None) for span in (protocol.rows, protocol.cols))
    image = at.to_recorded(rendered).clamp(0, 1)[:, rows, cols]
    captured = at.recorded_view(v)[:, rows, cols]
    return {"psnr": psnr(image, captured), "ssim": structural_similarity(image, captured),
            "detail": detail_correlation(image, captured, detail_sigma(at)),
            "psnr_black": psnr(torch.zeros_like(captured), captured)}
