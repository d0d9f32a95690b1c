"""The Python API's own pieces: scenes by name, rendering, scoring and solvers in one call
each. The rest of the API (options, build, fit, reconstruct, load_run) is re-exported from
:mod:`flamerecon` where it lives. Every argument is checked here, by the CLI's rules where it
has one (:mod:`flamerecon.fit.option_rules`), before any work."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.arguments import instance, one_or_many, tensor, value, wrong_value
from flamerecon.errors import ArgumentError
from flamerecon.fit.option_rules import RULES, check_fields, leaves
from flamerecon.fit.options import SolverOptions
from flamerecon.fit.reconstruct import Reconstruction
from flamerecon.geometry.cameras import cameras_to
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.operators.projector import render_image
from flamerecon.run.folder import Run
from flamerecon.scenes import SCENE_KEYS, SCENE_LOADERS, Scene, register_built_in
from flamerecon.scenes import load_scene as load_scene_node
from flamerecon.solvers import Solver
from flamerecon.solvers import make_solver as make_solver_unchecked


def load_scene(scene: str | Mapping, **options) -> Scene:
    """A scene by loader name (``"synthetic"``, ``"scalarflow"``, ``"opencv"``, ``"nerf"``,
    ``"pinf"``) or by its options mapping (``{"name": ..., ...}`` as ``conf/scene/*.yaml``
    has them), with ``options`` on top, e.g. ``load_scene("synthetic", width=64, height=48)``.
    An option the loader does not read, or a value its ``scene.*`` rule refuses, is an
    :class:`~flamerecon.errors.ArgumentError` naming it."""
    instance("load_scene.scene", scene, (str, Mapping), "a scene name or a mapping of scene options")
    node = {**({"name": scene} if isinstance(scene, str) else dict(scene)), **options}
    name = node.get("name")
    register_built_in()
    if name not in SCENE_LOADERS:
        raise wrong_value("scene.name", name, f"one of {sorted(SCENE_LOADERS)}")
    known = SCENE_KEYS.get(name)
    unknown = [key for key in node if known is not None and key not in known]
    if unknown:
        raise ArgumentError(f"scene.{unknown[0]}: scene '{name}' has no option {unknown[0]!r}; its options "
                            f"are {sorted(known)}")
    if node.get("holdout") is not None:
        node["holdout"] = one_or_many(node["holdout"])  # one view, not its name's characters
    check_fields("", leaves({"scene": node}))
    return load_scene_node(node)


def render(volume: torch.Tensor, grid: VoxelGrid, cameras: PinholeCamera, step: float = 0.5) -> torch.Tensor:
    """Emission-only renders of a density (C, nz, ny, nx) on ``grid`` through kornia
    ``cameras`` (B of them, one size): (B, C, H, W) float32 line integrals on the density's
    device, ``step`` in voxels (>= 0.01, as ``projector.step``)."""
    instance("render.grid", grid, VoxelGrid)
    volume = tensor("render.volume", volume, "(C, nz, ny, nx) on the grid", shape=(None, *grid.shape), finite=True)
    instance("render.cameras", cameras, PinholeCamera, "a kornia PinholeCamera batch")
    sizes = {(int(h), int(w)) for h, w in zip(cameras.height.tolist(), cameras.width.tolist())}
    if len(sizes) != 1:
        raise wrong_value("render.cameras", sorted(sizes), "a batch of at least one camera, all of one image size")
    value("render.step", step, RULES["projector.step"].check)
    return render_image(volume.float(), grid, cameras_to(cameras, volume.device), float(step))


def score(result: Reconstruction | Run) -> dict:
    """The metrics of a :class:`~flamerecon.fit.reconstruct.Reconstruction` or a loaded
    :class:`~flamerecon.run.folder.Run`: held-out and training PSNR / SSIM (with the all-black
    floor), inside the silhouettes, and volume errors when the scene has a truth."""
    instance("score.result", result, (Reconstruction, Run), "a Reconstruction (reconstruct) or a Run (load_run)")
    tensor("score.result.density", result.density, "(C, nz, ny, nx) on the result's grid",
           shape=(None, *result.grid.shape), finite=True)
    return result.score()


def make_solver(name: str, **options) -> Solver:
    """The solver registered as ``name`` with its own ``options`` (``max_iters=100, tol=1e-4``),
    each checked by its rule ``solver.<option>`` as the CLI checks it."""
    SolverOptions(name, None, None, options)
    return make_solver_unchecked(name, **options)
