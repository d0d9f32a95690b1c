"""The tiny config's synthetic scene (5 cameras, 48x36), generated once per test session and
registered as ``scene.name=defective``, with ``++scene.defect=NAME`` breaking one thing in it;
and :func:`tiny_cfg`, the tiny config on it with the :data:`~.config.FAST` solve."""

from __future__ import annotations

import dataclasses
import functools

import torch
from kornia.geometry.camera import PinholeCamera
from omegaconf import OmegaConf

from flamerecon.geometry.silhouettes import silhouettes
from flamerecon.scenes import SCENE_LOADERS, register_scene
from flamerecon.scenes.synthetic import load as load_synthetic

from .config import FAST, tiny_config


def tiny_cfg(*overrides: str):
    """The tiny config with the FAST solve on the cached tiny synthetic scene (the one TINY
    describes; ``defective(...)`` breaks it)."""
    return tiny_config(*FAST, "scene.name=defective", "++scene.defect=none", *overrides)


@functools.lru_cache(maxsize=1)
def tiny_reconstruction():
    """``fr.reconstruct`` of a smaller synthetic scene (3 cameras at 24x18, an 8-cell grid, 5
    iterations): seconds, made once per session (the API tests share it; one that edits it
    puts it back)."""
    import flamerecon as fr

    scene = fr.load_scene({"name": "synthetic", "width": 24, "height": 18, "n_cameras": 3, "phantom_resolution": 16})
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=8), device="cpu",
                                       solver=fr.SolverOptions(params={"max_iters": 5}))
    return fr.reconstruct(scene, options)


@functools.lru_cache(maxsize=1)
def tiny_synthetic():
    return load_synthetic(OmegaConf.create({"name": "synthetic", "n_cameras": 5, "width": 48, "height": 36,
                                                "phantom_resolution": 32}))


def _defect(scene, defect: str):
    """A copy of the tiny synthetic scene with one thing broken."""
    cams = scene.cameras
    images, K4, E = scene.images.clone(), cams.intrinsics.clone(), cams.extrinsics.clone()
    width, views, masks = cams.width.clone(), list(scene.views), None
    if defect == "nan_image":
        images[1, 0, 5, 5] = float("nan")
    elif defect == "inf_image":
        images[0, 2, 1, 1] = float("inf")
    elif defect == "dark_view":
        images[2] = 0.0
    elif defect == "looks_away":  # turn camera 3 around its own y axis by 180 degrees
        E[3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0])) @ E[3]
    elif defect == "size_mismatch":
        width[0] = 50
    elif defect == "negative_focal":
        K4[1, 0, 0] = -K4[1, 0, 0]
    elif defect == "not_orthonormal":
        E[2, :3, :3] *= 1.1
    elif defect == "missing_view_name":
        views = views[1:]
    elif defect == "disjoint_silhouette":  # cam02's silhouette: a speck at its left edge
        masks = silhouettes(images)
        masks[2] = False
        masks[2, 17:19, :2] = True
    cams = PinholeCamera(K4, E, cams.height.clone(), width)
    return type(scene)(**{**scene.__dict__, "images": images, "cameras": cams, "views": views,
                          "masks": masks, "source": f"defective.json ({defect})"})


if "defective" not in SCENE_LOADERS:
    @register_scene("defective")
    def _load_defective(cfg):
        scene = tiny_synthetic()
        if cfg.get("unit") is not None:  # ++scene.unit=M: the tiny flame measured in M metres per unit
            scene = dataclasses.replace(scene, unit=float(cfg["unit"]))
        return scene if cfg["defect"] == "none" else _defect(scene, cfg["defect"])


def defective(defect: str) -> list[str]:
    return [f"++scene.defect={defect}"]
