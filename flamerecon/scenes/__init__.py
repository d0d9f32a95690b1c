"""Scene sources, one module each, all returning :class:`Scene`; chosen by ``scene.name``."""

from __future__ import annotations

from collections.abc import Callable

from .base import Scene, SceneError

#: scene name -> loader taking the ``scene`` config node (a mapping) and returning a Scene.
SCENE_LOADERS: dict[str, Callable[..., Scene]] = {}


def register_scene(name: str):
    def deco(fn):
        SCENE_LOADERS[name] = fn
        return fn

    return deco


def load_scene(cfg) -> Scene:
    """Load the scene described by the ``scene`` config node (needs ``cfg.name``)."""
    from . import nerf, opencv_calib, pinf, synthetic  # noqa: F401  (registers built-in loaders)

    name = cfg["name"]
    if name not in SCENE_LOADERS:
        raise SceneError(f"scene.name: unknown scene '{name}'; choose one of {sorted(SCENE_LOADERS)}")
    return SCENE_LOADERS[name](cfg)


__all__ = ["SCENE_LOADERS", "Scene", "SceneError", "load_scene", "register_scene"]
