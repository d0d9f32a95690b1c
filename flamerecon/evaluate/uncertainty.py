"""How well the cameras determine a reconstruction: a confidence volume (per voxel and channel,
the predicted one-sigma spread of the density) and, for any camera, a confidence image (per
pixel, the predicted one-sigma spread of the rendered value), from an ensemble of densities the
data leave about equally likely (:mod:`flamerecon.fit.ensemble`), and how to check them
against held-out errors.

The spread has one part per kind of member, each the mean squared deviation of its members
from the reconstruction ``x``:

- ``cameras``: the densities fitted with each training camera left out (what one camera fewer
  changes: where the views disagree or one camera alone carries a structure);
- ``weights``: the solver's weights perturbed (what the prior chose);
- ``shift``: ``x`` moved by ``shift_voxels`` along each axis, both ways (where a structure is,
  to a fraction of a voxel: the grid's and the views' resolution);
- ``poses``: the densities fitted to the training pixels as the training cameras moved by their
  measured pose offsets would record them (:mod:`flamerecon.fit.ensemble`).

The predicted variance is ``scale**2`` times the sum of the first three plus the ``poses``
part (a measured spread, not scaled): in the volume, of the voxel values; in an image, of the
rendered deviations (a pixel integrates its ray, so neighbouring voxels' deviations add before
they are squared), plus, for a camera of the scene named, its own pose's spread
(:mod:`flamerecon.evaluate.pose_spread`). ``scale`` is chosen on frames that are not reported
(docs/results.md).

Why this ensemble (against the Laplace posterior of the active set, and each kind alone), its
``scale``, and how it predicts held-out errors: docs/results.md, "What the cameras determine".
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import kornia
import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import fields, tensor, value, wrong_value
from flamerecon.evaluate.image_noise import NoiseModel, noise_model
from flamerecon.evaluate.pose_spread import PoseSpread
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.outputs.export import DensityFileError, save_density
from flamerecon.rules import number
from flamerecon.scenes import Scene

#: the deviation kinds of the spread, in the order they are summed
KINDS = ("cameras", "weights", "shift", "poses")
#: the kinds of solved members (``shift`` needs no solve)
SOLVED = ("cameras", "weights", "poses")



def translated(volume: torch.Tensor, axis: int, cells: int) -> torch.Tensor:
    """``volume`` (C, nz, ny, nx) moved by a whole number of ``cells`` along array axis
    ``axis`` (1: z, 2: y, 3: x), zero where nothing moved in."""
    if cells == 0:
        return volume
    out = torch.zeros_like(volume)
    n = volume.shape[axis]
    if abs(cells) >= n:
        return out
    src = [slice(None)] * volume.ndim
    dst = [slice(None)] * volume.ndim
    src[axis] = slice(0, n - cells) if cells > 0 else slice(-cells, n)
    dst[axis] = slice(cells, n) if cells > 0 else slice(0, n + cells)
    out[tuple(dst)] = volume[tuple(src)]
    return out


def shifted(volume: torch.Tensor, axis: int, voxels: float) -> torch.Tensor:
    """``volume`` (C, nz, ny, nx) moved by ``voxels`` (any real) along array axis ``axis``,
    linearly interpolated between whole cells (the trilinear interpolant's value along that
    axis), zero where nothing moved in."""
    whole = math.floor(voxels)
    part = voxels - whole
    out = translated(volume, axis, whole)
    return out if part == 0 else (1 - part) * out + part * translated(volume, axis, whole + 1)


def shift_deviations(volume: torch.Tensor, voxels: float):
    """The six deviations (C, nz, ny, nx) of ``volume`` moved by ``voxels`` along x, y and z,
    both ways, from ``volume``, one at a time (an iterator); none for 0."""
    if voxels == 0:
        return
    for axis in (3, 2, 1):
        for sign in (1, -1):
            yield shifted(volume, axis, sign * voxels) - volume


def mean_square(values) -> torch.Tensor:
    """The mean of the squares of the tensors ``values`` (an iterable, read once), summed one
    at a time."""
    total, count = None, 0
    for v in values:
        total = v.pow(2) if total is None else total.add_(v.pow(2))
        count += 1
    return total / count


@dataclass
class Confidence:
    """The confidence of a density ``x`` (M, C) on the hull voxels ``voxel_index`` (M,) of
    ``grid`` (``hull``: (nz, ny, nx) bool), from ensemble ``members`` (K, M, C) whose kinds
    (``cameras``, ``weights``) are ``groups``, ``shift_voxels`` and ``scale`` (see the module's
    docstring); ``step``: the renders' ray step in voxels; ``seconds``: what the members cost;
    ``poses``: the scene's cameras' pose uncertainty (:mod:`flamerecon.evaluate.pose_spread`),
    added, unscaled, to the images of the cameras it names."""

    grid: VoxelGrid
    voxel_index: torch.Tensor
    hull: torch.Tensor
    x: torch.Tensor
    members: torch.Tensor
    groups: list[str]
    shift_voxels: float
    scale: float
    step: float = 0.5
    seconds: float = 0.0
    labels: list[str] = field(default_factory=list)
    poses: PoseSpread | None = None

    def __post_init__(self) -> None:
        fields(self)
        self.hull = tensor("Confidence.hull", self.hull, "(nz, ny, nx) of the grid", shape=self.grid.shape, kind="bool")
        self.voxel_index = tensor("Confidence.voxel_index", self.voxel_index, "(M,) flat hull indices", ndim=1,
                                  kind="integer")
        M = int(self.voxel_index.numel())
        self.x = tensor("Confidence.x", self.x, "(M, C) hull values", shape=(M, None), finite=True)
        self.members = tensor("Confidence.members", self.members, "(K, M, C) hull values",
                              shape=(None, M, self.x.shape[1]), finite=True)
        if len(self.groups) != self.members.shape[0] or not set(self.groups) <= set(SOLVED):
            raise wrong_value("Confidence.groups", self.groups, f"one kind of {list(SOLVED)} per member "
                              f"({self.members.shape[0]})")
        value("Confidence.shift_voxels", self.shift_voxels, number(0, 2))  # uncertainty.shift_voxels' rule
        value("Confidence.scale", self.scale, number(0, lo_open=True))
        value("Confidence.step", self.step, number(0.01))  # projector.step's rule

    @property
    def density(self) -> torch.Tensor:
        """(C, nz, ny, nx) the reconstruction."""
        return self.grid.dense(self.x, self.voxel_index)

    def deviations(self):
        """(kind, iterator over its deviations (C, nz, ny, nx)) per kind that has members; each
        deviation is made when it is read, so memory holds one at a time."""
        density = self.density
        for kind in SOLVED:
            chosen = [m for m, g in zip(self.members, self.groups) if g == kind]
            if chosen:
                yield kind, (self.grid.dense(m - self.x, self.voxel_index) for m in chosen)
        if float(self.shift_voxels):
            yield "shift", shift_deviations(density, float(self.shift_voxels))

    def variance_parts(self) -> dict[str, torch.Tensor]:
        """Per kind, the mean squared deviation (C, nz, ny, nx) of its members, unscaled."""
        return {kind: mean_square(devs) for kind, devs in self.deviations()}

    def scaled(self, parts: dict[str, torch.Tensor], like: torch.Tensor) -> torch.Tensor:
        """The predicted variance from unscaled ``parts``: ``scale**2`` times every kind's but
        ``poses``' (a measured spread, taken as it is) plus that; zeros like ``like`` for none."""
        total = like.new_zeros(like.shape)
        for kind, part in parts.items():
            total = total + (part if kind == "poses" else float(self.scale) ** 2 * part)
        return total

    def volume(self) -> torch.Tensor:
        """The confidence volume (C, nz, ny, nx): the predicted one-sigma spread of each voxel's
        density, in the density's units (0 where the data and the hull leave nothing free)."""
        return self.scaled(self.variance_parts(), self.density).sqrt()

    def image_parts(self, cams: PinholeCamera) -> dict[str, torch.Tensor]:
        """Per kind, the mean squared rendered deviation (B, C, H, W) through ``cams``, unscaled."""
        cams = cameras_to(cams, self.x.device)
        return {kind: mean_square(render_image(d, self.grid, cams, self.step) for d in devs)
                for kind, devs in self.deviations()}

    def image(self, cams: PinholeCamera, views: list[str | None] | None = None) -> torch.Tensor:
        """The confidence images (B, C, H, W) of ``cams``: per pixel the predicted one-sigma
        spread of the rendered value (image units, before a camera's photometry). ``views``
        (B): the scene's name of each camera (None: a novel one), whose pose uncertainty
        (:attr:`poses`) adds its variance; None: no camera's is added."""
        B, H, W = cams.batch_size, int(cams.height[0]), int(cams.width[0])
        variance = self.scaled(self.image_parts(cams), self.x.new_zeros(B, self.x.shape[1], H, W))
        if self.poses is not None and views is not None:
            variance = variance + self.poses.variance(self.density, self.grid, cameras_to(cams, self.x.device),
                                                      list(views), self.step)
        return variance.sqrt()

    def footprint(self, cams: PinholeCamera) -> torch.Tensor:
        """(B, H, W) bool: the pixels of ``cams`` whose ray meets the visual hull, where the
        reconstruction can be nonzero (the silhouettes of every training camera carved the
        rest; only the shifts reach a fraction of a voxel beyond)."""
        ones = self.hull[None].to(self.x.dtype)
        return render_image(ones, self.grid, cameras_to(cams, self.x.device), self.step)[:, 0] > 0


def predicted_psnr(sigma: torch.Tensor, max_val: float = 1.0) -> float:
    """The PSNR (dB) a render would score if its errors had the predicted spread ``sigma``
    (C, H, W): ``10 log10(max_val^2 / mean(sigma^2))`` over the full frame, as
    :func:`~flamerecon.evaluate.metrics.psnr` averages squared errors."""
    mse = float(sigma.double().pow(2).mean())
    return math.inf if mse == 0 else 10.0 * math.log10(max_val**2 / mse)


def ranks(values: torch.Tensor) -> torch.Tensor:
    """Ranks (n,) float64 of ``values`` (n,), 1-based, ties given their mean rank."""
    v = values.double().reshape(-1)
    order = torch.argsort(v)
    sorted_v = v[order]
    n = v.numel()
    new = torch.ones(n, dtype=torch.bool)
    new[1:] = sorted_v[1:] != sorted_v[:-1]
    group = torch.cumsum(new, 0) - 1  # tie group of each sorted value
    position = torch.arange(1, n + 1, dtype=torch.float64)
    count = torch.zeros(int(group[-1]) + 1 if n else 0, dtype=torch.float64).index_add_(0, group, torch.ones(n, dtype=torch.float64))
    total = torch.zeros_like(count).index_add_(0, group, position)
    out = torch.empty(n, dtype=torch.float64)
    out[order] = (total / count)[group]
    return out


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """The Spearman rank correlation of ``a`` and ``b`` (same number of values): Pearson's of
    their ranks (ties: mean ranks); NaN where either is constant."""
    ra, rb = ranks(a), ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    den = float((ra.pow(2).sum() * rb.pow(2).sum()).sqrt())
    return float((ra * rb).sum()) / den if den > 0 else math.nan


def coverage(error: torch.Tensor, sigma: torch.Tensor, k: float) -> float:
    """The fraction of values whose ``|error|`` is at most ``k`` times ``sigma`` (same shape)."""
    return float((error.abs() <= k * sigma).double().mean()) if error.numel() else math.nan


#: the scales (pixels) of :func:`neighbour_rms`, the oracle :func:`check_view` reports
ORACLE_PX = (2.0, 4.0)


def neighbour_rms(error: torch.Tensor, px: float) -> torch.Tensor:
    """(C, H, W): at each pixel the RMS of ``error`` (C, H, W) over its neighbours, weighted by
    a Gaussian of ``px`` pixels with the pixel itself left out (reflected at the border). An
    oracle that knows the error around a pixel but not at it: what a predictor of spread at
    that resolution could at best do."""
    size = min(2 * math.ceil(3 * px) + 1, 2 * min(error.shape[-2:]) - 1)
    kernel = kornia.filters.get_gaussian_kernel1d(size, px).double()
    centre = float(kernel[0, size // 2]) ** 2
    blurred = kornia.filters.gaussian_blur2d(error.double().pow(2)[None], (size, size), (px, px),
                                             border_type="reflect")[0]
    return ((blurred - centre * error.double().pow(2)) / (1 - centre)).clamp_min(0).sqrt()


def check_view(rendered: torch.Tensor, captured: torch.Tensor, sigma: torch.Tensor, domain: torch.Tensor,
               silhouette: torch.Tensor | None = None) -> dict[str, float]:
    """How a confidence image ``sigma`` (C, H, W) predicts the error of ``rendered`` (C, H, W,
    clipped to [0, 1] as :func:`~flamerecon.evaluate.metrics.psnr` does) against ``captured``,
    in the pixels of ``domain`` (H, W) bool (every channel):

    - ``spearman``: the rank correlation of ``sigma`` with ``|error|``; ``spearman_trivial``:
      that of the rendered intensity, the baseline (errors grow where the plume is bright);
    - ``coverage_1sigma`` / ``coverage_2sigma``: the fraction of pixels with ``|error| <= k
      sigma``; ``*_trivial``: the same for the rendered intensity times the gain that makes its
      mean square the error's over the full frame (fitted on this very view: generous to it);
    - ``psnr`` (full frame, measured) and ``psnr_predicted`` (:func:`predicted_psnr`);
    - ``spearman_frame`` / ``spearman_frame_trivial``: over the full frame (mostly background,
      where both are 0); with ``silhouette`` (H, W) bool also ``spearman_silhouette`` /
      ``spearman_silhouette_trivial`` inside it;
    - ``spearman_oracle_<n>px``: that of :func:`neighbour_rms` of the error itself at each scale
      of :data:`ORACLE_PX` (a diagnosis, never a predictor: it reads the held-out image).
    """
    r = rendered.detach().double().cpu().clamp(0, 1)
    error = (r - captured.detach().double().cpu()).abs()
    s = sigma.detach().double().cpu()
    gain = math.sqrt(float(error.pow(2).mean()) / max(float(r.pow(2).mean()), 1e-300))
    trivial = gain * r
    inside = domain.cpu().expand_as(error)
    out = {
        "spearman": spearman(s[inside], error[inside]),
        "spearman_trivial": spearman(r[inside], error[inside]),
        "coverage_1sigma": coverage(error[inside], s[inside], 1.0),
        "coverage_2sigma": coverage(error[inside], s[inside], 2.0),
        "coverage_1sigma_trivial": coverage(error[inside], trivial[inside], 1.0),
        "coverage_2sigma_trivial": coverage(error[inside], trivial[inside], 2.0),
        "psnr": 10.0 * math.log10(1.0 / max(float(error.pow(2).mean()), 1e-300)),
        "psnr_predicted": predicted_psnr(s),
        "spearman_frame": spearman(s, error),
        "spearman_frame_trivial": spearman(r, error),
        "domain_fraction": float(domain.double().mean()),
    }
    for px in ORACLE_PX:
        out[f"spearman_oracle_{px:g}px"] = spearman(neighbour_rms(error, px)[inside], error[inside])
    if silhouette is not None:
        sil = silhouette.cpu().expand_as(error)
        out.update(spearman_silhouette=spearman(s[sil], error[sil]),
                   spearman_silhouette_trivial=spearman(r[sil], error[sil]))
    return out


def recorded_sigma(scene: Scene, rendered: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """The spread ``sigma`` of renders (..., C, H, W) in the units ``scene``'s cameras record
    (what a view is scored in, :meth:`~flamerecon.scenes.Scene.to_recorded`): the response
    curve's step from the render to the render plus sigma; ``sigma`` itself for a linear camera."""
    if scene.response is None:
        return sigma
    return (scene.to_recorded(rendered + sigma) - scene.to_recorded(rendered)).abs()


def capture_sigma(scene: Scene, rendered: torch.Tensor, sigma: torch.Tensor, noise: NoiseModel) -> torch.Tensor:
    """The predicted spread (..., C, H, W) of the error of renders ``rendered`` (..., C, H, W, of
    spread ``sigma``) against their cameras' captures, in recorded units: the render's own spread
    (:func:`recorded_sigma`) and the sensor ``noise`` at the render's recorded intensity, added
    in variance (the capture is the true image plus its noise)."""
    spread = recorded_sigma(scene, rendered, sigma)
    level = scene.to_recorded(rendered.clamp(0, 1))
    return (spread.pow(2) + noise.variance(level)).sqrt()


def training_noise(scene: Scene, train: list[int]) -> NoiseModel:
    """The sensor noise of ``scene``'s cameras, from its training views ``train`` as recorded
    (:func:`~flamerecon.evaluate.image_noise.noise_model`); a held-out view is never read."""
    return noise_model(torch.stack([scene.recorded_view(v) for v in train]))


def save_confidence(path: str | os.PathLike, conf: Confidence, views: list[str]) -> Path:
    """``uncertainty.npz`` of a run: ``density``: the confidence volume (C, nz, ny, nx) float32
    (as in density.npz, so every export reads it), ``bbox_min``, ``bbox_max``, ``views`` (those
    fitted), and what :func:`load_confidence` needs to render confidence images again: ``x``
    (M, C) and ``members`` (K, M, C) on the hull voxels ``voxel_index`` (M,), ``labels`` (K,),
    ``shift_voxels``, ``scale``, ``step``, ``seconds``, and with :attr:`Confidence.poses` its
    fields as ``pose_<field>``."""
    grid = conf.grid
    poses = {} if conf.poses is None else {f"pose_{k}": pose_array(getattr(conf.poses, k)) for k in POSE_FIELDS}
    return save_density(path, conf.volume().cpu(), grid.bbox_min, grid.bbox_max, views,
                        x=conf.x.cpu(), members=conf.members.cpu(), voxel_index=conf.voxel_index.cpu(),
                        labels=np.array(conf.labels or conf.groups, dtype=np.str_).reshape(-1),
                        resolution=np.array(grid.resolution), shift_voxels=float(conf.shift_voxels),
                        scale=float(conf.scale), step=float(conf.step), seconds=float(conf.seconds), **poses)


#: the fields of a :class:`~flamerecon.evaluate.pose_spread.PoseSpread` that uncertainty.npz keeps
POSE_FIELDS = ("views", "K", "world_to_camera", "share", "rotation_deg", "box_px", "lost_db", "sources")


def pose_array(value) -> np.ndarray:
    """A PoseSpread field as a numpy array (names as strings)."""
    return value.cpu().numpy() if isinstance(value, torch.Tensor) else np.array(value, dtype=np.str_).reshape(-1)


def load_confidence(path: str | os.PathLike, device: torch.device | str = "cpu") -> Confidence:
    """The :class:`Confidence` :func:`save_confidence` wrote (a run's ``uncertainty.npz``)."""
    path = Path(path)
    with np.load(path) as f:
        missing = [k for k in ("x", "members", "voxel_index", "labels", "resolution", "bbox_min", "bbox_max",
                               "shift_voxels", "scale", "step") if k not in f.files]
        if missing:
            raise DensityFileError(f"{path}: missing field '{missing[0]}'; is it a run's uncertainty.npz?")
        grid = VoxelGrid(tuple(f["bbox_min"].tolist()), tuple(f["bbox_max"].tolist()),
                         tuple(int(n) for n in f["resolution"]))
        index = torch.from_numpy(f["voxel_index"]).long().to(device)
        hull = torch.zeros(grid.num_voxels, dtype=torch.bool, device=device)
        hull[index] = True
        labels = [str(s) for s in f["labels"]]
        poses = None
        if "pose_views" in f.files:
            read = {k: f[f"pose_{k}"] for k in POSE_FIELDS}
            poses = PoseSpread(**{k: [str(s) for s in v] if v.dtype.kind == "U" else torch.from_numpy(v)
                                  for k, v in read.items()})
        return Confidence(grid, index, hull.reshape(grid.shape), torch.from_numpy(f["x"]).to(device),
                          torch.from_numpy(f["members"]).to(device), [s.split(":", 1)[0] for s in labels],
                          float(f["shift_voxels"]), float(f["scale"]), float(f["step"]),
                          float(f["seconds"]) if "seconds" in f.files else 0.0, labels, poses)
