"""Scene sources, one module each, all returning :class:`Scene`; chosen by ``scene.name``."""

from __future__ import annotations

from collections.abc import Callable

from flamerecon.plain import plain
from flamerecon.scenes.base import Scene, SceneError

#: scene name -> loader taking the ``scene`` config node (a mapping) and returning a Scene.
SCENE_LOADERS: dict[str, Callable[..., Scene]] = {}


def register_scene(name: str):
    def deco(fn):
        SCENE_LOADERS[name] = fn
        return fn

    return deco


def load_scene(cfg) -> Scene:
    """Load the scene described by the ``scene`` config node (needs ``cfg.name``); the scene
    keeps the node as plain Python in ``meta["config"]`` (see :func:`load_frame`)."""
    from flamerecon.scenes import nerf, opencv_calib, pinf, synthetic  # noqa: F401  (registers built-in loaders)

    name = cfg["name"]
    if name not in SCENE_LOADERS:
        raise SceneError(f"scene.name: unknown scene '{name}'; choose one of {sorted(SCENE_LOADERS)}")
    scene = SCENE_LOADERS[name](cfg)
    scene.meta.setdefault("config", plain(cfg))
    return scene


def load_frame(scene: Scene, frame: int) -> Scene:
    """Frame ``frame`` of the capture ``scene`` was loaded from (same source and options)."""
    config = scene.meta.get("config")
    if config is None:
        raise SceneError(f"scene '{scene.name}' was not loaded by load_scene, so its other frames are "
                         "unknown; load it with flamerecon.load_scene")
    return load_scene({**config, "frame": int(frame)})


__all__ = ["SCENE_LOADERS", "Scene", "SceneError", "load_frame", "load_scene", "register_scene"]
