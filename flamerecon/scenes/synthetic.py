"""The built-in synthetic flame: a procedural, turbulent RGB emission field filmed by a ring
of cameras, with images rendered from a finer phantom and finer ray steps than any
reconstruction uses, plus sensor noise (no inverse crime).

World units are arbitrary lengths; y is up. The flame stands on y = 0 inside the box
x, z in [-0.5, 0.5], y in [0, 1.5]. ``frame`` advances time (a rising, flickering flame).

Harder, more real variants (conf/scene/synthetic_flame.yaml): ``field: smooth`` (a smooth,
laminar flame, as a real flame looks at camera resolution, instead of the turbulent one),
``azimuths`` (unevenly spaced cameras) and ``calibration_error`` (the cameras the solver is
given are off by that many pixels; the images were rendered by the true ones).
"""

from __future__ import annotations

import math
import sys

import torch
import torch.nn.functional as F

from flamerecon.errors import MemoryBudgetError
from flamerecon.geometry.axes import UP_AXES, axis_name, turn_box, turn_from_y, turn_volume
from flamerecon.geometry.cameras import intrinsics_matrix, look_at, make_cameras
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.machine import MEMORY_SHARE, available_bytes, format_bytes
from flamerecon.operators.projector import render_image
from flamerecon.scenes import register_scene
from flamerecon.scenes.base import Scene, SceneError
from flamerecon.scenes.cache import cached
from flamerecon.scenes.values import (
    NONNEGATIVE,
    POSITIVE,
    read_array,
    read_float,
    read_int,
    read_text,
)

#: the modules whose code makes the rendered scene (part of its cache key)
_RENDER_CODE = ("flamerecon.scenes.synthetic", "flamerecon.operators.projector", "flamerecon.geometry.grid", "flamerecon.geometry.cameras")

BOX_MIN = (-0.5, 0.0, -0.5)
BOX_MAX = (0.5, 1.5, 0.5)
SECONDS_PER_FRAME = 1.0 / 30.0


def _noise(points: torch.Tensor, seed: int, octaves: int = 3, base: int = 5) -> torch.Tensor:
    """Fractal value noise in about [-1, 1] at world points (…, 3), periodic over 4 units."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    out = torch.zeros(points.shape[:-1], device=points.device)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = base * 2**o
        lattice = torch.rand(1, 1, n, n, n, generator=g) * 2 - 1
        lattice = F.pad(lattice, (0, 1, 0, 1, 0, 1), mode="circular").to(points.device)  # seamless
        coords = torch.remainder(points / 4.0 + 0.37 * o, 1.0) * 2 - 1  # periodic lookup
        vals = F.grid_sample(
            lattice, coords.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="reflection",
            align_corners=True,
        )
        out = out + amp * vals.reshape(points.shape[:-1])
        total += amp
        amp *= 0.5
    return out / total * 1.7


def flame_emission(points: torch.Tensor, seed: int = 0, time: float = 0.0) -> torch.Tensor:
    """RGB emission density (…, 3) at world points (…, 3) at ``time`` seconds.

    A teardrop of hot gas on y = 0 whose outline is pushed around by turbulence that rises
    with the flow: a bright yellow-white core, redder and fainter towards the edge, and
    flickering tongues at the top.
    """
    x, y, z = points.unbind(-1)
    rise = 0.9 * time  # turbulence is carried upwards
    advected = torch.stack([x, y - rise, z], -1)
    h = (y / 1.25).clamp(0.0, 1.0)
    amp = 0.05 + 0.2 * h**1.3
    sway = 0.06 * h**1.5 * math.sin(2 * math.pi * 1.7 * time)
    xd = x + amp * _noise(advected * 2.0, seed + 1) + sway
    zd = z + amp * _noise(advected * 2.0, seed + 2)
    r = torch.sqrt(xd**2 + zd**2)
    radius = 0.3 * (1 - h) ** 0.75 * ((h + 0.02) / 0.12).clamp(max=1.0) ** 0.5
    radius = radius * (1 + 0.3 * _noise(advected * 3.0, seed + 3))
    heat = (1 - r / radius.clamp_min(1e-4)).clamp(0, 1) ** 1.2
    tongues = torch.sigmoid(8 * (_noise(advected * 2.5, seed + 4) + 1.1 - 1.6 * h))
    temp = heat * tongues * (1 - 0.55 * h) * (y > 0)
    rgb = torch.stack([temp**0.8, 0.9 * temp**1.4, 0.7 * temp**2.5], -1)
    return rgb


def smooth_flame_emission(points: torch.Tensor, seed: int = 0, time: float = 0.0) -> torch.Tensor:
    """RGB emission density (…, 3) of a smooth, laminar flame at world points (…, 3).

    A candle- or burner-like flame: a Gaussian cross-section around a centreline that leans and
    sways slowly (low-frequency noise only, no tongues, no sharp edge), widest a third of the
    way up, fading smoothly towards its tip; the same colours as :func:`flame_emission`.
    """
    x, y, z = points.unbind(-1)
    advected = torch.stack([x, y - 0.5 * time, z], -1)
    h = (y / 1.2).clamp(0.0, 1.0)
    lean = 0.12 * h**1.5
    sway = 0.03 * h**1.5 * math.sin(2 * math.pi * 0.8 * time)
    cx = lean * _noise(advected * 0.6, seed + 1, octaves=1, base=3) + sway
    cz = lean * _noise(advected * 0.6, seed + 2, octaves=1, base=3)
    r2 = (x - cx) ** 2 + (z - cz) ** 2
    width = 0.28 * (h + 0.03).clamp(max=1.0) ** 0.35 * (1 - h).clamp_min(0) ** 0.7 + 1e-3
    width = width * (1 + 0.15 * _noise(advected * 0.8, seed + 3, octaves=1, base=3))
    foot = torch.sigmoid((y - 0.03) / 0.015)  # the burner's rim: smooth, not a cut
    temp = torch.exp(-r2 / (2 * width**2)) * (1 - 0.6 * h) * foot * (h < 1)
    rgb = torch.stack([temp**0.8, 0.9 * temp**1.4, 0.7 * temp**2.5], -1)
    return rgb


#: the emission fields of ``scene.field``
FIELDS = {"turbulent": flame_emission, "smooth": smooth_flame_emission}


def flame_volume(grid: VoxelGrid, seed: int = 0, time: float = 0.0, device=None,
                 field: str = "turbulent") -> torch.Tensor:
    """The flame (``field``: a key of :data:`FIELDS`) sampled at the cell centres of ``grid``:
    (3, nz, ny, nx)."""
    return FIELDS[field](grid.centers(device), seed, time).permute(3, 0, 1, 2).contiguous()


def ring_cameras(n: int, width: int, height: int, radius: float = 3.0, focal: float | None = None,
                 azimuths=None):
    """``n`` cameras on a horizontal ring around the flame, alternating between two
    elevations, looking at its middle; ``azimuths`` (n degrees) place them, else evenly
    spaced. Returns a kornia camera batch."""
    angles = (torch.arange(n, dtype=torch.float64) * 2 * math.pi / n if azimuths is None
              else torch.deg2rad(torch.as_tensor(azimuths, dtype=torch.float64)))
    elev = torch.deg2rad(10.0 + 8.0 * (-1.0) ** torch.arange(n, dtype=torch.float64))
    target = torch.tensor([0.0, 0.62, 0.0], dtype=torch.float64)
    eye = torch.stack(
        [radius * torch.cos(elev) * torch.sin(angles), target[1] + radius * torch.sin(elev),
         radius * torch.cos(elev) * torch.cos(angles)], -1,
    )
    f = focal if focal is not None else 470.0 * height / 240.0
    K = intrinsics_matrix(f, f, width / 2.0, height / 2.0).expand(n, 3, 3)
    return make_cameras(K, look_at(eye, target.expand(n, 3)), height, width)


def miscalibrated(cams, pixels: float, seed: int):
    """``cams`` with a calibration error of ``pixels``: each camera turned about its own centre
    by a random small rotation that shifts its image by ``pixels`` in a random direction, plus a
    random roll about its axis that moves a point a quarter of the image height from the
    principal point by up to half that. The same ``seed``, the same errors."""
    g = torch.Generator(device="cpu").manual_seed(seed + 4242)
    n = cams.batch_size
    f = cams.intrinsics[:, 0, 0].double()
    direction = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    tilt = pixels / f  # radians: a rotation about an axis across the view shifts by f * angle
    roll = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 0.5 * pixels / (0.25 * cams.height.double())
    omega = torch.stack([tilt * torch.sin(direction), tilt * torch.cos(direction), roll], -1)  # camera axes
    theta = omega.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = omega / theta
    Kx = torch.zeros(n, 3, 3, dtype=torch.float64)
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx = Kx - Kx.transpose(1, 2)
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    dR = torch.eye(3, dtype=torch.float64) + s * Kx + (1 - c) * Kx @ Kx  # Rodrigues
    E = cams.extrinsics.double().clone()
    E[:, :3, :3] = dR @ E[:, :3, :3]  # about the camera centre: R' = dR R, t' = dR t
    E[:, :3, 3:] = dR @ E[:, :3, 3:]
    return make_cameras(cams.intrinsics[:, :3, :3], E, cams.height, cams.width)


def _crop_to_support(volume: torch.Tensor, grid: VoxelGrid) -> tuple[torch.Tensor, VoxelGrid]:
    """The smallest sub-grid (same cells, one empty cell of border) holding every nonzero."""
    nz_ = volume.abs().sum(0).nonzero()
    if nz_.numel() == 0:
        return volume, grid
    lo_k = (nz_.amin(0) - 1).clamp_min(0)
    hi_k = nz_.amax(0) + 2
    size = grid.voxel_size()
    lo_ijk, hi_ijk = lo_k.flip(0), hi_k.flip(0)  # (k, j, i) -> (i, j, k)
    sub = VoxelGrid(
        tuple((grid.lo() + lo_ijk * size).tolist()),
        tuple((grid.lo() + hi_ijk.minimum(torch.tensor(grid.resolution)) * size).tolist()),
        tuple((hi_ijk.minimum(torch.tensor(grid.resolution)) - lo_ijk).tolist()),
    )
    v = volume[:, lo_k[0]:hi_k[0], lo_k[1]:hi_k[1], lo_k[2]:hi_k[2]]
    return v.contiguous(), sub


def downscale(images: torch.Tensor, cams, factor: int):
    """Area-average images (B, C, H, W) by an integer ``factor`` and scale the cameras'
    intrinsics to match (pixel centres at +0.5 scale exactly with the size ratio), as the
    capture loaders' ``scene.downscale`` does. Returns (images, cameras)."""
    if factor == 1:
        return images, cams
    H, W = images.shape[-2:]
    h, w = H // factor, W // factor
    if h < 1 or w < 1:
        raise SceneError(f"config: scene.downscale: {factor} leaves no pixels of a {W}x{H} image")
    # cropping the right and bottom remainder keeps pixel coordinates, so K scales by 1/factor
    small = F.interpolate(images[..., : h * factor, : w * factor], size=(h, w), mode="area")
    S = torch.diag(torch.tensor([1.0 / factor, 1.0 / factor, 1.0]))
    K = S.to(cams.intrinsics.dtype) @ cams.intrinsics[:, :3, :3]
    return small, make_cameras(K, cams.extrinsics, h, w)


#: bytes per phantom cell while the phantom is made (its points, noise octaves, the volume)
PHANTOM_BYTES_PER_CELL = 96
#: bytes per pixel and channel of the images while they are made (clean, noise, noisy, scaled)
IMAGE_BYTES_PER_VALUE = 32
#: bytes per camera (kornia's 4x4 intrinsics and extrinsics, the look-at temporaries)
CAMERA_BYTES = 1024


def check_memory(n: int, width: int, height: int, truth_grid: VoxelGrid) -> None:
    """Refuse, naming the option, a scene whose phantom or images would not fit in the memory
    free now (:class:`~flamerecon.errors.MemoryBudgetError`): torch would otherwise fail
    halfway, or the machine swap."""
    free = available_bytes("cpu")
    if free is None:
        return
    phantom = math.prod(truth_grid.resolution) * PHANTOM_BYTES_PER_CELL
    images = n * (width * height * 3 * IMAGE_BYTES_PER_VALUE + CAMERA_BYTES)
    if phantom + images <= MEMORY_SHARE * free:
        return
    if phantom >= images:
        what = (f"scene.phantom_resolution: a {'x'.join(map(str, truth_grid.resolution))} phantom needs about "
                f"{format_bytes(phantom)}")
        fix = "a smaller scene.phantom_resolution (128 is the default)"
    else:
        what = (f"scene.n_cameras x scene.width x scene.height: {n} images of {width}x{height} px need about "
                f"{format_bytes(images)}")
        fix = "fewer or smaller images (scene.n_cameras, scene.width, scene.height)"
    raise MemoryBudgetError(f"config: {what} while it is made, but {format_bytes(free)} is free; use {fix}")


@register_scene("synthetic", keys=("n_cameras", "width", "height", "downscale", "frame", "seed",
                                         "phantom_resolution", "phantom_step", "noise", "peak", "field",
                                         "azimuths", "calibration_error", "up", "unit"))
def load(cfg) -> Scene:
    """Config keys: n_cameras, width, height (the native size), downscale (the working size is
    width // downscale x height // downscale), phantom_resolution, phantom_step, noise, frame,
    seed, peak (brightest pixel before noise), field (turbulent | smooth), azimuths (null:
    evenly spaced; else n_cameras angles in degrees), calibration_error (pixels of the native
    images by which every camera given to the solver, held-out ones too, is off from the one
    that rendered its image; fixed by the seed, the same on every frame), up (the axis the
    flame rises along, ``+y`` by default: the whole scene, cameras, box and truth, turned by
    :func:`~flamerecon.geometry.axes.turn_from_y`; the images stay the same), unit (metres per
    world unit: null, the flame's lengths are world units, unless given)."""
    n = read_int(cfg.get("n_cameras", 8), "config", "scene.n_cameras", 2)
    W, H = (read_int(cfg.get(k, default), "config", f"scene.{k}") for k, default in (("width", 320), ("height", 240)))
    seed = read_int(cfg.get("seed", 0), "config", "scene.seed", 0)
    frame = read_int(cfg.get("frame", 0), "config", "scene.frame", 0)
    field = read_text(cfg.get("field", "turbulent"), "config", "scene.field")
    if field not in FIELDS:
        raise SceneError(f"config: scene.field: got '{field}'; it must be one of {sorted(FIELDS)}")
    azimuths = cfg.get("azimuths", None)
    if azimuths is not None:
        azimuths = read_array(azimuths, "config", "scene.azimuths")
        if azimuths.shape != (n,):
            raise SceneError(f"config: scene.azimuths: got {azimuths.tolist()}; it must be a list of "
                             f"scene.n_cameras = {n} angles in degrees (or null: evenly spaced)")
        azimuths = [float(a) for a in azimuths]
    error_px = read_float(cfg.get("calibration_error", 0.0), "config", "scene.calibration_error", NONNEGATIVE)
    phantom = read_int(cfg.get("phantom_resolution", 128), "config", "scene.phantom_resolution", 2)
    truth_grid = VoxelGrid.from_box(BOX_MIN, BOX_MAX, phantom)
    check_memory(n, W, H, truth_grid)
    cams = ring_cameras(n, W, H, azimuths=azimuths)
    step = read_float(cfg.get("phantom_step", 0.5), "config", "scene.phantom_step", POSITIVE)

    def render() -> dict[str, torch.Tensor]:
        truth = flame_volume(truth_grid, seed, frame * SECONDS_PER_FRAME, field=field)
        cropped, sub = _crop_to_support(truth, truth_grid)
        return {"truth": truth, "clean": render_image(cropped, sub, cams, step=step)}

    options = {"n_cameras": n, "width": W, "height": H, "seed": seed, "frame": frame,
               "phantom_resolution": phantom, "phantom_step": step,
               **({"field": field} if field != "turbulent" else {}),  # the default's cache key as before
               **({"azimuths": azimuths} if azimuths is not None else {})}
    found = cached("synthetic", options, render, [sys.modules[m] for m in _RENDER_CODE])
    truth, clean = found["truth"], found["clean"]
    peak = read_float(cfg.get("peak", 0.85), "config", "scene.peak", POSITIVE)
    scale = peak / float(clean.max().clamp_min(1e-12))
    clean, truth = clean * scale, truth * scale
    g = torch.Generator(device="cpu").manual_seed(seed + 1000 * frame + 7)
    sigma = read_float(cfg.get("noise", 0.01), "config", "scene.noise", NONNEGATIVE)
    # read noise sigma, growing with brightness like photon noise: std = sigma * sqrt(1 + 4 I)
    std = sigma * torch.sqrt(1 + 4 * clean.clamp_min(0))
    images = (clean + std * torch.randn(clean.shape, generator=g)).clamp(0, 1)
    if error_px > 0:  # the images stay the true cameras' renders
        cams = miscalibrated(cams, error_px, seed)
    images, cams = downscale(images, cams, read_int(cfg.get("downscale", 1), "config", "scene.downscale"))
    up = axis_name(cfg.get("up", "+y"))
    if up is None:
        raise SceneError(f"config: scene.up: got {cfg.get('up')!r}; give the axis the flame rises along, one of "
                         f"{', '.join(UP_AXES)}")
    Q = turn_from_y(up)
    box = turn_box(BOX_MIN, BOX_MAX, Q)
    views = [f"cam{i:02d}" for i in range(n)]
    return Scene(
        name="synthetic", views=views, cameras=turned_cameras(cams, Q), images=images,
        bbox_min=box[0], bbox_max=box[1], default_holdout=[views[-1]],
        truth=turn_volume(truth, Q), truth_grid=VoxelGrid.from_box(*turn_box(BOX_MIN, BOX_MAX, Q), phantom),
        source=f"synthetic {'' if field == 'turbulent' else field + ' '}flame (seed {seed}, frame {frame})",
        meta={"frame": frame, "noise": sigma, "time": frame * SECONDS_PER_FRAME,
              **({"field": field} if field != "turbulent" else {}),
              **({"calibration_error": error_px} if error_px > 0 else {})},
        up=up, up_source="config scene.up" if "up" in cfg and cfg.get("up") is not None else "the synthetic flame's own (+y)",
        frame_rate=1.0 / SECONDS_PER_FRAME, unit=None if cfg.get("unit") is None else read_float(
            cfg["unit"], "config", "scene.unit", POSITIVE),
    )


def turned_cameras(cams, Q: torch.Tensor):
    """The camera batch ``cams`` in a world turned by ``Q`` (x' = Q x): each sees the same image."""
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = Q.T
    w2c = cams.extrinsics.double() @ turn
    return make_cameras(cams.intrinsics[:, :3, :3], w2c.float(), cams.height, cams.width)
