"""The one scene type every loader returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import fields, one_or_many, tensor
from flamerecon.errors import FlameReconError
from flamerecon.geometry.axes import UP_AXES, axis_name
from flamerecon.geometry.grid import VoxelGrid, checked_box
from flamerecon.geometry.photometry import delinearize
from flamerecon.geometry.units import length_name


class SceneError(FlameReconError, ValueError):
    """Bad scene input; the message names the file and the field."""


@dataclass
class Scene:
    """Calibrated views of one frame.

    - ``views``: camera names, one per image;
    - ``cameras``: kornia camera batch (B), OpenCV world->camera, pixel centres at +0.5;
    - ``images``: (B, C, H, W) float32 in [0, 1], linear in emitted radiance;
    - ``bbox_min`` / ``bbox_max``: world xyz of the box that holds the density;
    - ``default_holdout``: view names held out when the config does not say;
    - ``masks``: optional (B, H, W) bool silhouettes when the source provides them;
    - ``truth`` / ``truth_grid``: optional ground-truth density (C, nz, ny, nx) for synthetic scenes;
    - ``source``: where the scene came from (file or generator), for messages;
    - ``response``: {"gamma", "black_level"} when ``images`` were linearized from
      ``recorded_images`` (B, C, H, W), the values as the cameras recorded them; scores are
      taken in those units (:meth:`to_recorded`, :meth:`recorded_view`);
    - ``up``: the world axis the flame rises along, one of ``"+x"`` ... ``"-z"``
      (:mod:`flamerecon.geometry.axes`); ``up_source`` says where it came from (the config, the
      calibration file, the cameras' image-up directions, or the scene's own convention);
    - ``unit``: metres per world unit (None: unknown; lengths are then in world units);
    - ``frame_rate``: frames per second of the capture (None: unknown);
    - ``meta``: loader extras.
    """

    name: str
    views: list[str]
    cameras: PinholeCamera
    images: torch.Tensor
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    default_holdout: list[str] = field(default_factory=list)
    masks: torch.Tensor | None = None
    truth: torch.Tensor | None = None
    truth_grid: VoxelGrid | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)
    response: dict | None = None
    recorded_images: torch.Tensor | None = None
    up: str = "+y"
    up_source: str = "the default"
    unit: float | None = None
    frame_rate: float | None = None

    def __post_init__(self) -> None:
        self.views, self.default_holdout = one_or_many(self.views), one_or_many(self.default_holdout)
        self.bbox_min, self.bbox_max = checked_box(self.bbox_min, self.bbox_max, "Scene")
        where = self.source or "Scene"
        if axis_name(self.up) is None:
            raise SceneError(f"{where}: up: {self.up!r} is not an axis; give one of {', '.join(UP_AXES)}")
        self.up = axis_name(self.up)
        for key in ("unit", "frame_rate"):
            number = getattr(self, key)
            if number is not None and not (isinstance(number, (int, float)) and not isinstance(number, bool)
                                           and 0 < float(number) < float("inf")):
                raise SceneError(f"{where}: {key}: {number!r} is not a positive number (or None: unknown)")
            setattr(self, key, None if number is None else float(number))
        fields(self)
        for name in self.views:
            if not isinstance(name, str) or not name or any(ord(ch) < 32 or ord(ch) == 127 for ch in name):
                raise SceneError(f"{self.source or 'Scene.views'}: view name {name!r} is empty or holds a control "
                                 "character (NUL, newline, tab, ...); name each view with printable text")
        images = tensor("Scene.images", self.images, "(B, C, H, W) in [0, 1]", ndim=4)
        self.images = images.float()  # float32, as every loader gives them
        B, _, H, W = images.shape
        tensor("Scene.masks", self.masks, "(B, H, W) silhouettes", shape=(B, H, W), kind="bool", null=True)
        tensor("Scene.truth", self.truth, "(C, nz, ny, nx)", ndim=4, null=True)
        tensor("Scene.recorded_images", self.recorded_images, "(B, C, H, W) like images", shape=images.shape,
               null=True)

    def to_recorded(self, images: torch.Tensor) -> torch.Tensor:
        """Linear images (..., C, H, W), e.g. renders, in the units the cameras record (the
        response curve and black level re-applied), to be scored against :meth:`recorded_view`."""
        if self.response is None:
            return images
        return delinearize(images, self.response["gamma"], self.response["black_level"])

    def recorded_view(self, v: int) -> torch.Tensor:
        """View ``v`` (C, H, W) as its camera recorded it."""
        return self.images[v] if self.recorded_images is None else self.recorded_images[v]

    def length_unit(self) -> str:
        """The name of a length on this scene's world axes: ``"m"`` when one world unit is a
        metre, ``"mm"`` for a millimetre, else ``"world units"`` (or ``"x <unit> m"``)."""
        return length_name(self.unit)

    @property
    def num_views(self) -> int:
        return len(self.views)

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W)."""
        return int(self.images.shape[-2]), int(self.images.shape[-1])

    def split(self, holdout) -> tuple[list[int], list[int]]:
        """Resolve ``holdout`` (view names or indices; None for the scene's default) into
        (train indices, held-out indices). None held out (``[]``, or None where the scene names
        no default) fits every camera: nothing then scores the result on a view it did not see
        (leave-one-view-out does)."""
        if holdout is None:
            holdout = list(self.default_holdout)
        if isinstance(holdout, (str, int)):
            holdout = [holdout]
        held: list[int] = []
        for h in holdout:
            if isinstance(h, int) or (isinstance(h, str) and h.lstrip("-").isdigit() and h not in self.views):
                i = int(h)
                if not -self.num_views <= i < self.num_views:
                    raise SceneError(
                        f"holdout: view index {i} is out of range; scene '{self.name}' has "
                        f"{self.num_views} views: {self.views}"
                    )
                i %= self.num_views
            elif h in self.views:
                i = self.views.index(h)
            else:
                raise SceneError(f"holdout: unknown view '{h}'; scene '{self.name}' has views {self.views}")
            if i not in held:
                held.append(i)
        train = [i for i in range(self.num_views) if i not in held]
        if not train:
            raise SceneError(f"holdout: {list(holdout)} holds out every view of scene '{self.name}'; keep at least one for training")
        self.check_no_leak(train, held)
        return train, held

    def check_no_leak(self, train: list[int], held: list[int]) -> None:
        """Refuse a held-out view whose image is also among the training views (a capture
        that lists one frame twice): its score would measure the fit, not a prediction."""
        fitted = {}
        for t in train:
            fitted.setdefault(self._image_key(t), t)
        for h in held:
            t = fitted.get(self._image_key(h))
            if t is not None and torch.equal(self.images[h], self.images[t]) and bool(
                    self.images[h].amax() > self.images[h].amin()):
                raise SceneError(
                    f"{self.source or 'holdout'}: held-out view '{self.views[h]}' has the same image as "
                    f"training view '{self.views[t]}'; drop the duplicate from the scene or hold out both"
                )

    def _image_key(self, v: int) -> tuple:
        """A cheap fingerprint of view ``v``'s image (equal images give equal keys)."""
        img = self.images[v]
        return (tuple(img.shape), float(img.double().sum()), float((img.double() ** 2).sum()))

