"""What each camera's pose uncertainty does to its renders: the camera's pose moved both ways
by the offset the data ask of it (:mod:`flamerecon.fit.pose_uncertainty` measures it), and per
pixel the variance ``share * mean((render(+) - render)^2, (render(-) - render)^2)``, where
``share`` is the part of that change the captured images confirmed where the offset was
measured (1: all of it). Renders are compared clipped to [0, 1], as a view is scored."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import fields, tensor
from flamerecon.geometry.cameras import make_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image


@dataclass
class PoseSpread:
    """Per camera ``views`` (B names): the camera moved by plus and minus its pose offset,
    ``K`` (B, 2, 3, 3) and ``world_to_camera`` (B, 2, 4, 4), the ``share`` (B,) of that change
    its images confirmed, its one-sigma rotation ``rotation_deg`` (B,) and the shift of the
    box's corners ``box_px`` (B,) in pixels, the PSNR its pose error cost its images where the
    offset was measured ``lost_db`` (B,), and where the offset came from (``sources``)."""

    views: list[str]
    K: torch.Tensor
    world_to_camera: torch.Tensor
    share: torch.Tensor
    rotation_deg: torch.Tensor
    box_px: torch.Tensor
    lost_db: torch.Tensor
    sources: list[str]

    def __post_init__(self) -> None:
        fields(self)
        B = len(self.views)
        self.K = tensor("PoseSpread.K", self.K, "(B, 2, 3, 3)", shape=(B, 2, 3, 3), finite=True)
        self.world_to_camera = tensor("PoseSpread.world_to_camera", self.world_to_camera, "(B, 2, 4, 4)",
                                      shape=(B, 2, 4, 4), finite=True)
        for name in ("share", "rotation_deg", "box_px", "lost_db"):
            setattr(self, name, tensor(f"PoseSpread.{name}", getattr(self, name), "(B,)", shape=(B,), finite=True))

    def moved(self, view: str, like: PinholeCamera) -> PinholeCamera:
        """The two moved cameras (2) of ``view``, of ``like``'s image size (one camera)."""
        k = self.views.index(view)
        return make_cameras(self.K[k], self.world_to_camera[k], like.height.expand(2), like.width.expand(2))

    def variance(self, volume: torch.Tensor, grid: VoxelGrid, cams: PinholeCamera, views: list[str | None],
                 step: float = 0.5) -> torch.Tensor:
        """(B, C, H, W): per pixel of each camera of ``cams`` (B, named ``views``; a name
        without an offset, or None, adds 0) the variance its pose uncertainty gives the render of
        ``volume`` (C, nz, ny, nx), see the module's docstring."""
        B, C = cams.batch_size, volume.shape[0]
        H, W = int(cams.height[0]), int(cams.width[0])
        out = volume.new_zeros(B, C, H, W)
        for b, view in enumerate(views):
            if view not in self.views:
                continue
            cam = PinholeCamera(*(t[b:b + 1] for t in (cams.intrinsics, cams.extrinsics, cams.height, cams.width)))
            base = render_image(volume, grid, cam, step).clamp(0, 1)
            moved = render_image(volume, grid, self.moved(view, cam), step).clamp(0, 1)
            out[b] = float(self.share[self.views.index(view)]) * (moved - base).pow(2).mean(0)
        return out

    def records(self) -> dict[str, dict]:
        """{view: ``pose_sigma_deg``, ``pose_sigma_box_px``, ``pose_share``, ``pose_lost_db``,
        ``pose_source``}."""
        return {v: {"pose_sigma_deg": float(self.rotation_deg[k]), "pose_sigma_box_px": float(self.box_px[k]),
                    "pose_share": float(self.share[k]), "pose_lost_db": float(self.lost_db[k]),
                    "pose_source": self.sources[k]}
                for k, v in enumerate(self.views)}

    def limiting(self) -> str | None:
        """The camera whose pose error cost its images the most PSNR where it was measured
        (``lost_db``): the calibration to distrust first (None: no camera)."""
        return self.views[int(self.lost_db.argmax())] if self.views else None
