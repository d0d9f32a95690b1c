"""The Python API's own pieces: presets and scenes by name as the command line has them,
rendering, scoring, solvers and exports in one call each. The rest of the API (options, build,
fit, reconstruct, load_run, cameras) is re-exported from :mod:`flamerecon` where it lives.
Every argument is checked here, by the CLI's rules where it has one
(:mod:`flamerecon.fit.option_rules`), before any work."""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import instance, one_or_many, tensor, value, wrong_type, wrong_value
from flamerecon.device import resolve_device
from flamerecon.dynamics.conventions import frame_rate_of
from flamerecon.dynamics.flow import Flow, FlowOptions
from flamerecon.dynamics.flow import estimate_flow as estimate_flow_core
from flamerecon.dynamics.sequence import FrameFacts, check_sequence
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.evaluate.uncertainty import Confidence, load_confidence
from flamerecon.fit.build import build, hull_values
from flamerecon.fit.ensemble import confidence as solve_confidence
from flamerecon.fit.option_rules import RULES, check_fields, leaves
from flamerecon.fit.options import ReconstructionOptions, SolverOptions
from flamerecon.fit.reconstruct import Reconstruction
from flamerecon.fit.uncertainty_options import UncertaintyOptions
from flamerecon.geometry.axes import ground_frame, up_vector
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import camera_rays, integrate_dense, render_image
from flamerecon.outputs.atomic import make_folder
from flamerecon.outputs.export import (
    ALIASES,
    DENSITY_FILE,
    FORMATS,
    UNCERTAINTY_FILE,
    Density,
    export_density,
    load_density,
    recorded_conventions,
    sigma_names,
)
from flamerecon.outputs.figures import _angles, orbit_cameras, write_png
from flamerecon.outputs.mesh import DEFAULT_ISO
from flamerecon.outputs.sequence import SweepError, find_frame_runs
from flamerecon.resources import config_dir
from flamerecon.rules import integer, number
from flamerecon.run.folder import Run, load_run
from flamerecon.scenes import SCENE_KEYS, SCENE_LOADERS, Scene, register_built_in
from flamerecon.scenes import load_scene as load_scene_node
from flamerecon.solvers import Solver
from flamerecon.solvers import make_solver as make_solver_unchecked


def preset(scene: str = "synthetic", *overrides: str) -> ReconstructionOptions:
    """The options ``python train.py scene=<scene> <overrides...>`` reconstructs with, composed
    from the same ``conf/`` files by Hydra: ``preset("scalarflow")``, ``preset("synthetic",
    "solver=fista", "grid.resolution=48")``. Scenes: ``conf/scene/*.yaml``."""
    instance("preset.scene", scene, str, "a scene name of conf/scene/*.yaml")
    for k, o in enumerate(overrides):
        instance(f"preset.overrides[{k}]", o, str, "a command-line override key=value")
    from flamerecon.run.preset import preset as composed
    from flamerecon.run.preset import scene_presets

    if scene not in scene_presets():
        raise wrong_value("preset.scene", scene, f"a preset of conf/scene/: one of {scene_presets()}")
    try:
        return composed(scene, *overrides)
    except ArgumentError:
        raise
    except ConfigError as err:  # Hydra's word on an override: the override is the argument at fault
        raise ArgumentError(f"preset.{err}" if str(err).startswith("overrides") else str(err)) from None


def load_scene(scene: str | Mapping = "synthetic", **options) -> Scene:
    """A scene as the command line loads it: by preset name (``"synthetic"``, ``"scalarflow"``:
    the ``scene:`` node of ``conf/scene/<name>.yaml``, e.g. ScalarFlow frame 59 at 1/4
    resolution from ``$FLAMERECON_DATA`` or ``../shared/data/scalarflow_real``), by loader name
    (``"pinf"``), or by its options mapping (``{"name": ..., ...}``); ``options`` on top, e.g.
    ``load_scene("scalarflow", frame=25)`` or ``load_scene("opencv", root="capture/")``.
    An option the loader does not read, or a value its ``scene.*`` rule refuses, is an
    :class:`~flamerecon.errors.ArgumentError` naming it."""
    instance("load_scene.scene", scene, (str, Mapping), "a scene name or a mapping of scene options")
    register_built_in()
    node = {"name": scene} if isinstance(scene, str) else dict(scene)
    if isinstance(scene, str) and (config_dir() / "scene" / f"{scene}.yaml").is_file():
        from flamerecon.run.preset import scene_preset  # Hydra composes it, as for the command line

        node = scene_preset(scene)
    given = set(options) | (set() if isinstance(scene, str) else set(node))
    node = {**node, **options}
    frames = node.pop("frames", None)  # the scene node's run-level key: the frames a run solves jointly
    if frames is not None and "frames" in given:
        raise wrong_value("scene.frames", frames, "None here: load_scene loads one frame (scene.frame); load "
                          "each and solve them jointly with fr.reconstruct_frames")
    name = node.get("name")
    if name not in SCENE_LOADERS:
        raise wrong_value("scene.name", name, f"one of {sorted(SCENE_LOADERS)}")
    known = SCENE_KEYS.get(name)
    unknown = [key for key in node if key in given and known is not None and key not in known]
    if unknown:
        raise ArgumentError(f"scene.{unknown[0]}: scene '{name}' has no option {unknown[0]!r}; its options "
                            f"are {sorted(known)}")
    if node.get("holdout") is not None:
        node["holdout"] = one_or_many(node["holdout"])  # one view, not its name's characters
    # a preset's value left ??? (None) is the loader's to name ("no data folder given"); given ones are checked
    check_fields("", leaves({"scene": {k: v for k, v in node.items() if k in given or v is not None}}))
    return load_scene_node(node)


def render(volume: torch.Tensor, grid: VoxelGrid, cameras: PinholeCamera, step: float = 0.5) -> torch.Tensor:
    """Emission-only renders of a density (C, nz, ny, nx) on ``grid`` through kornia
    ``cameras`` (B of them, one size; :func:`flamerecon.look_at_camera`,
    :func:`flamerecon.orbit_cameras` or a scene's): (B, C, H, W) float32 line integrals on the density's
    device, ``step`` in voxels (>= 0.01, as ``projector.step``).

    Differentiable: for a ``volume`` that requires grad (and grad enabled) the renders keep the
    autograd graph, every pixel marched (a zero voxel's gradient counts too); otherwise only the pixels the nonzero density projects onto are marched."""
    instance("render.grid", grid, VoxelGrid)
    volume = tensor("render.volume", volume, "(C, nz, ny, nx) on the grid", shape=(None, *grid.shape), finite=True)
    instance("render.cameras", cameras, PinholeCamera, "a kornia PinholeCamera batch")
    sizes = {(int(h), int(w)) for h, w in zip(cameras.height.tolist(), cameras.width.tolist())}
    if len(sizes) != 1:
        raise wrong_value("render.cameras", sorted(sizes), "a batch of at least one camera, all of one image size")
    value("render.step", step, RULES["projector.step"].check)
    cams = cameras_to(cameras, volume.device)
    if volume.requires_grad and torch.is_grad_enabled():
        (H, W), = sizes
        rays, _ = camera_rays(cams)
        pixels = integrate_dense(volume.float(), grid, rays, float(step))  # (B H W, C)
        return pixels.T.reshape(volume.shape[0], cams.batch_size, H, W).transpose(0, 1)
    return render_image(volume.float(), grid, cams, float(step))


def score(result: Reconstruction | Run) -> dict:
    """The metrics of a :class:`~flamerecon.fit.reconstruct.Reconstruction` or a loaded
    :class:`~flamerecon.run.folder.Run`: held-out and training PSNR / SSIM (with the all-black
    floor), inside the silhouettes, volume errors when the scene has a truth, and ``warnings``:
    ``[{"code", "message"}]`` for a result that means little (an empty density, saturated views,
    an all-black held-out view, see :mod:`flamerecon.evaluate.result_warnings`)."""
    instance("score.result", result, (Reconstruction, Run), "a Reconstruction (reconstruct) or a Run (load_run)")
    tensor("score.result.density", result.density, "(C, nz, ny, nx) on the result's grid",
           shape=(None, *result.grid.shape), finite=True)
    return result.score()


def confidence(result: Reconstruction | Run, options: UncertaintyOptions | None = None) -> Confidence:
    """What the cameras determine in ``result`` (a Reconstruction, or a Run from
    :func:`~flamerecon.run.folder.load_run`, whose ``uncertainty.npz`` is read when it has
    one): the :class:`~flamerecon.evaluate.uncertainty.Confidence` from the ensemble of
    ``options`` (default: the result's ``uncertainty`` options; ScalarFlow's preset carries the
    scale chosen for it), solved here (a solve per member, warm-started). Keep it to render
    several cameras: ``conf.image(cameras)`` (B, C, H, W) spreads, ``conf.volume()``
    (C, nz, ny, nx); ``fr.export(conf, stem)`` writes the volume."""
    instance("confidence.result", result, (Reconstruction, Run), "a Reconstruction (reconstruct) or a Run (load_run)")
    instance("confidence.options", options, UncertaintyOptions, null=True)
    if isinstance(result, Run):
        saved = result.folder / UNCERTAINTY_FILE
        if options is None and saved.is_file():
            return load_confidence(saved, result.density.device)
        run_options = result.options
        chosen = (result.solver.get("selection") or {}).get("chosen")
        if chosen:  # the weights the run chose at run time (select.auto)
            run_options = run_options.replace(solver=run_options.solver.with_values(**chosen))
        setup = build(result.scene, run_options, result.density.device)
        x = hull_values(result.density, setup.grid, setup.voxel_index).to(setup.pixels)
        return solve_confidence(setup, run_options, x, options, result.calibration)
    return solve_confidence(result.setup, result.options, result.fit.result.x, options, result.calibration)


def uncertainty(result: Reconstruction | Run | Confidence, cameras: PinholeCamera,
                views: list[str | None] | None = None) -> torch.Tensor:
    """The confidence images (B, C, H, W) of ``cameras`` (B of them, one size; held-out,
    training or novel: :func:`flamerecon.look_at_camera`, :func:`flamerecon.orbit_cameras`):
    per pixel the predicted one-sigma spread of the rendered value of ``result``'s density, in
    image units. ``views``: each camera's name in the scene (None: a novel camera), whose pose
    uncertainty the capture's calibration measured adds to its image. A Reconstruction or Run
    has its :func:`confidence` solved first (keep that to render more cameras without solving
    again)."""
    instance("uncertainty.result", result, (Reconstruction, Run, Confidence),
             "a Reconstruction, a Run or a Confidence (fr.confidence)")
    instance("uncertainty.cameras", cameras, PinholeCamera, "a kornia PinholeCamera batch")
    if views is not None and (not isinstance(views, (list, tuple)) or len(views) != cameras.batch_size
                              or not all(v is None or isinstance(v, str) for v in views)):
        raise wrong_value("uncertainty.views", views, f"a list of {cameras.batch_size} camera names (or None)")
    sizes = {(int(h), int(w)) for h, w in zip(cameras.height.tolist(), cameras.width.tolist())}
    if len(sizes) != 1:
        raise wrong_value("uncertainty.cameras", sorted(sizes), "a batch of at least one camera, all of one image size")
    found = result if isinstance(result, Confidence) else confidence(result)
    return found.image(cameras, None if views is None else list(views))


def make_solver(name: str, **options) -> Solver:
    """The solver registered as ``name`` with its own ``options`` (``max_iters=100, tol=1e-4``),
    each checked by its rule ``solver.<option>`` as the CLI checks it."""
    SolverOptions(name, None, None, options)
    return make_solver_unchecked(name, **options)


def export(result, stem: str | os.PathLike, formats: Iterable[str] | str = ("vti",),
           iso: float = DEFAULT_ISO) -> list[Path]:
    """Write the density of ``result`` (a Reconstruction, a loaded Run, or a run folder or
    density.npz; or the confidence volume of a :func:`confidence`) for other tools as ``<stem>.<format>``: ``vti`` (ParaView), ``nrrd``, ``raw``
    (+ ``.raw.json``), the iso-surface mesh at ``iso`` times the peak density as ``ply`` and
    ``obj`` (Blender, ParaView; ``mesh``: both), ``all``; returns the files written. Placed in
    metres where the scene knows its unit (``scene.unit``), else in world units."""
    instance("export.result", result, (Reconstruction, Run, Confidence, str, os.PathLike),
             "a Reconstruction, a Run, a Confidence (its volume), or a run folder or density.npz")
    instance("export.stem", stem, (str, os.PathLike), "a path without suffix")
    if not Path(stem).name or "\0" in str(stem) or Path(stem).is_dir():
        raise wrong_value("export.stem", stem, "a file path without suffix (e.g. 'out/flame'), not empty, not a folder, "
                          "without NUL characters")
    value("export.iso", iso, RULES["export.iso"].check)
    names = [formats] if isinstance(formats, str) else formats
    instance("export.formats", names, Iterable, "a format name or a list of them")
    names = list(names)
    for k, name in enumerate(names):
        instance(f"export.formats[{k}]", name, str, "a format name")
    known = [*FORMATS, *ALIASES]
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise wrong_value("export.formats", formats, f"one or more of {known}")
    unit = getattr(getattr(result, "scene", None), "unit", None)  # placed in metres where the scene knows its unit
    if isinstance(result, (str, os.PathLike)):
        volume = load_density(result)
        folder = Path(result) if Path(result).is_dir() else Path(result).parent
        unit = recorded_conventions(folder)["unit"]
    elif isinstance(result, Confidence):
        grid = result.grid
        volume = Density(result.volume().detach().cpu().numpy().astype(np.float32), np.array(grid.bbox_min),
                         np.array(grid.bbox_max), [])
    else:
        views = getattr(result, "train", None) or result.setup.train
        grid = result.grid
        volume = Density(result.density.detach().cpu().numpy().astype(np.float32), np.array(grid.bbox_min),
                         np.array(grid.bbox_max), [result.scene.views[v] for v in views])
    if Path(stem).parent.exists() and not Path(stem).parent.is_dir():
        raise wrong_value("export.stem", stem, f"a path in a folder ({Path(stem).parent} is a file)")
    make_folder(Path(stem).parent)
    names = sigma_names(volume.density.shape[0]) if isinstance(result, Confidence) else None
    return export_density(volume, stem, formats, iso, names, unit)


def view(result, port: int = 8080, host: str = "127.0.0.1", device: str = "auto"):
    """Serve ``result`` (a Reconstruction, a loaded Run, a run folder or a multirun folder) to a
    browser, as ``flamerecon view`` does, and return the :class:`~flamerecon.viewer.server.Viewer`
    while it serves in the background: open its ``url``, call its ``stop()`` when done. A host
    that does not resolve or is not this machine's, or no free port from ``port`` on, is a
    ConfigError before anything is served. Needs ``pip install 'flamerecon[view]'``."""
    instance("view.result", result, (Reconstruction, Run, str, os.PathLike),
             "a Reconstruction, a Run, or a run or multirun folder")
    value("view.port", port, integer(1, 65535))
    instance("view.host", host, str, "an address such as 127.0.0.1")
    instance("view.device", device, (str, torch.device), "a device name (auto, cpu, cuda)")
    resolve_device(device, "view.device")
    from flamerecon.viewer.address import Fields
    from flamerecon.viewer.server import Viewer

    viewer = Viewer(result, host, port, str(device), fields=Fields("view.host", "view.port"))
    print(f"flamerecon view: open {viewer.url}")
    return viewer


RULE_FOV = number(0.0, 180.0, lo_open=True, hi_open=True)


def framing_camera(result, azimuth_deg=0.0, elevation_deg: float = 15.0, width: int = 320, height: int = 240,
                   fov_deg: float = 40.0) -> PinholeCamera:
    """Cameras that frame the flame of ``result`` (a Reconstruction or a loaded Run): on a circle
    around the density's support (voxels above 1% of the peak), at the distance where it fills
    the ``fov_deg`` (vertical) view, upright along the scene's up axis (``scene.up``); one per
    azimuth (degrees about that axis, 0 on the side of the first camera). A kornia batch
    for :func:`render`: ``fr.render(rec.density, rec.grid, fr.framing_camera(rec, [0, 90]))``."""
    instance("framing_camera.result", result, (Reconstruction, Run), "a Reconstruction or a Run")
    density = tensor("framing_camera.result.density", result.density, "(C, nz, ny, nx) on the result's grid",
                     shape=(None, *result.grid.shape), finite=True)
    value("framing_camera.width", width, integer(1))
    value("framing_camera.height", height, integer(1))
    value("framing_camera.fov_deg", fov_deg, RULE_FOV)
    value("framing_camera.elevation_deg", elevation_deg, number(-90.0, 90.0))
    lo, hi = np.asarray(result.grid.bbox_min, float), np.asarray(result.grid.bbox_max, float)
    near, far = emission_box(density.detach().float().cpu().numpy(), lo, hi)
    target = (near + far) / 2
    rotations = result.scene.cameras.extrinsics[:, :3, :3].double().cpu().numpy()
    up = np.asarray(up_vector(result.scene.up))
    toward = -rotations[0, 2, :]  # from the box towards the first camera
    axis = ground_frame(up)[0]
    azimuths = _angles("framing_camera.azimuth_deg", azimuth_deg)
    azimuths = azimuths + float(np.degrees(np.arctan2(toward @ np.cross(up, axis), toward @ axis)))
    probe = orbit_cameras(azimuths, elevation_deg, 1.0, target, width, height, fov_deg, up)
    distance = _fitting_distance(probe.extrinsics.double().numpy(), near, far, target, width, height, fov_deg)
    return orbit_cameras(azimuths, elevation_deg, distance, target, width, height, fov_deg, up)


def emission_box(density: np.ndarray, lo: np.ndarray, hi: np.ndarray, share: float = 0.98
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The world box (min xyz, max xyz) holding the middle ``share`` of the emission (channels
    summed) along each axis: where the light is, faint haze left out; the whole box when empty."""
    total = np.clip(density.sum(0), 0, None)  # (nz, ny, nx)
    if total.sum() <= 0:
        return lo, hi
    size = (hi - lo) / np.array(total.shape[::-1])
    near, far = lo.copy(), hi.copy()
    for axis in range(3):  # x, y, z
        profile = total.sum(axis=tuple(a for a in range(3) if a != 2 - axis))
        cumulative = np.cumsum(profile) / profile.sum()
        first = int(np.searchsorted(cumulative, (1 - share) / 2))
        last = int(np.searchsorted(cumulative, 1 - (1 - share) / 2))
        near[axis], far[axis] = lo[axis] + first * size[axis], lo[axis] + (last + 1) * size[axis]
    return near, far


def _fitting_distance(w2c: np.ndarray, near: np.ndarray, far: np.ndarray, target: np.ndarray, width: int,
                      height: int, fov_deg: float, margin: float = 1.1) -> float:
    """The distance from ``target`` at which every corner of the box [near, far] lies inside
    the image of each camera orientation of ``w2c`` (B, 4, 4), with ``margin`` to spare."""
    corners = np.array([[(near, far)[(p >> a) & 1][a] for a in range(3)] for p in range(8)]) - target
    focal = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
    need = 0.0
    for rotation in w2c[:, :3, :3]:
        x, y, z = corners @ rotation.T[:, 0], corners @ rotation.T[:, 1], corners @ rotation.T[:, 2]
        need = max(need, float(np.max(np.abs(x) * margin * focal / (width / 2) - z)),
                   float(np.max(np.abs(y) * margin * focal / (height / 2) - z)))
    return max(need, 1e-6 + float(np.max(-corners @ w2c[0, 2, :3])))


def save_image(path: str | os.PathLike, image: torch.Tensor, vmax: float | None = 1.0) -> Path:
    """Write a rendered or captured image (C, H, W) (or a batch of one) as a PNG, atomically:
    three channels in colour, one in grey, ``vmax`` shown white (1: the captures' scale, at which
    a render looks like its capture; None: the image's own maximum). Returns the path."""
    instance("save_image.path", path, (str, os.PathLike), "a file path ending in .png")
    if not str(path).lower().endswith(".png"):
        raise wrong_value("save_image.path", path, "a file path ending in .png")
    image = tensor("save_image.image", image, "(C, H, W) or (1, C, H, W)", finite=True)
    if image.ndim == 4 and image.shape[0] == 1:
        image = image[0]
    if image.ndim != 3 or image.shape[0] not in (1, 3):
        raise wrong_value("save_image.image", image, "an image (C, H, W) with C = 1 or 3, or a batch of one")
    if vmax is not None:
        value("save_image.vmax", vmax, number(0.0, lo_open=True))
    top = float(image.max()) if vmax is None else float(vmax)
    scaled = (image.detach().float().cpu() / (top or 1.0)).clamp(0, 1).expand(3, -1, -1)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_png(path, np.ascontiguousarray((scaled.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)))


def _sweep_runs(path: str | os.PathLike, device) -> list[Run]:
    """The frames of a multirun folder ``path`` as Runs (a single run folder is refused: a
    flow needs two frames)."""
    folder = Path(path)
    if (folder / DENSITY_FILE).is_file():
        raise ArgumentError(f"estimate_flow.frames: {folder} is one run folder (one frame); a flow needs two or more: "
                            "give the multirun folder that holds a run per frame, or a list of Runs")
    try:
        runs = find_frame_runs(folder)
    except (FileNotFoundError, SweepError) as err:
        raise ArgumentError(f"estimate_flow.frames: {err}; give a multirun folder of consecutive frames' runs "
                            "(python train.py -m scene.frame=...)") from None
    return [load_run(r.run_dir, str(device) if device is not None else "auto") for r in runs]


def _trained(frame: Reconstruction | Run) -> list[int]:
    """The view indices ``frame`` was fitted to."""
    return list(frame.train) if isinstance(frame, Run) else list(frame.setup.train)


def estimate_flow(frames: Sequence[Reconstruction | Run] | str | os.PathLike, options: FlowOptions | None = None,
                  device: torch.device | str | None = None) -> Flow:
    """The velocity of every consecutive pair of ``frames`` (Reconstructions of
    :func:`~flamerecon.fit.reconstruct.reconstruct`, run folders read back by
    :func:`~flamerecon.run.folder.load_run`, or the path of a multirun folder whose run folders
    are the frames; consecutive frames of one capture on one grid box, fitted to the same
    cameras, in order: :func:`~flamerecon.dynamics.sequence.check_sequence`), each fitted to the
    next frame's training images (:func:`flamerecon.dynamics.flow.estimate_flow`). A Run's
    operator is built again, one frame at a time (a Reconstruction brings its own). The frame
    rate is ``options.frame_rate``, else the capture's. Returns a
    :class:`~flamerecon.dynamics.flow.Flow`: ``flow.pairs[i].u`` in cells per frame,
    ``flow.velocity(i, "world")`` in world units per second."""
    if isinstance(frames, (str, os.PathLike)):
        frames = _sweep_runs(frames, device)
    if isinstance(frames, (Reconstruction, Run)) or not isinstance(frames, Sequence):
        raise wrong_type("estimate_flow.frames", frames, "a list of Reconstructions or Runs (consecutive frames), "
                         "or a multirun folder's path")
    for i, frame in enumerate(frames):
        instance(f"estimate_flow.frames[{i}]", frame, (Reconstruction, Run), "a Reconstruction or a Run")
    instance("estimate_flow.options", options, FlowOptions, null=True)
    instance("estimate_flow.device", device, (str, torch.device), "a device name (auto, cpu, cuda, cuda:N)", null=True)
    options = options or FlowOptions()
    numbers = [frame.scene.meta.get("frame") for frame in frames]
    check_sequence([FrameFacts(f"estimate_flow.frames[{i}] (frame {numbers[i]})", numbers[i], frame.grid.bbox_min,
                               frame.grid.bbox_max, tuple(frame.grid.shape), int(frame.density.shape[0]),
                               tuple(frame.scene.views[v] for v in _trained(frame)))
                    for i, frame in enumerate(frames)], "estimate_flow.frames", api=True)
    grid = frames[0].grid
    frame_rate = frame_rate_of(frames[0].scene, options.frame_rate)
    target = resolve_device(str(device)) if device is not None else frames[0].density.device

    def next_setup(i: int):
        frame = frames[i]
        if isinstance(frame, Reconstruction):
            return frame.setup
        return build(frame.scene, frame.options, target, frame.grid)

    densities = [frame.density.detach().to(target) for frame in frames]
    return estimate_flow_core(densities, next_setup, grid, options,
                              [n if isinstance(n, int) else i for i, n in enumerate(numbers)], frame_rate)
