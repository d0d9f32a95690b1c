"""Scene sources, one module each, all returning :class:`Scene`; chosen by ``scene.name``."""

from __future__ import annotations

from collections.abc import Callable

from flamerecon.plain import plain
from flamerecon.scenes.base import Scene, SceneError

#: scene name -> loader taking the ``scene`` config node (a mapping) and returning a Scene.
SCENE_LOADERS: dict[str, Callable[..., Scene]] = {}
#: scene name -> the keys of the ``scene`` node its loader reads (``name`` included).
SCENE_KEYS: dict[str, frozenset[str]] = {}


def register_scene(name: str, keys: tuple[str, ...] | None = None):
    """Register a loader as ``scene.name=name``; ``keys``: the options it reads (the API
    refuses others by name; None: any)."""

    def deco(fn):
        SCENE_LOADERS[name] = fn
        if keys is not None:
            SCENE_KEYS[name] = frozenset(("name", *keys))
        return fn

    return deco


def register_built_in() -> None:
    """Register the loaders that ship with flamerecon (imported on first use: they are heavy)."""
    from flamerecon.scenes import nerf, opencv_calib, pinf, plume, synthetic  # noqa: F401  (registers built-in loaders)


def load_scene(cfg) -> Scene:
    """Load the scene described by the ``scene`` config node (needs ``cfg.name``); the scene
    keeps the node as plain Python in ``meta["config"]`` (see :func:`load_frame`)."""
    register_built_in()
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


def capture_frames(scene: Scene) -> list[int]:
    """The frame numbers every camera of the capture ``scene`` was read from holds, in order
    (:func:`~flamerecon.scenes.frames.source_frames` of the files of ``meta["files"]``, those
    common to all; a camera given as one image holds every number), [0] for a scene without
    files (a synthetic one). A SceneError names two cameras whose frame numbers do not meet."""
    from flamerecon.scenes.frames import source_frames

    common: set[int] | None = None
    first = None
    for file in scene.meta.get("files") or []:
        found = source_frames(file)
        if found is None:
            continue
        if common is not None and not common & set(found):
            raise SceneError(f"{file}: holds frames {found[0]}-{found[-1]}, none of which {first} holds; the "
                             "cameras of one capture hold the same frame numbers (rename the frames, or give "
                             "calibration.frames=[...] the frames to fit the cameras to)")
        common = set(found) if common is None else common & set(found)
        first = first or file
    return sorted(common) if common else [0]


def load_downscaled(scene: Scene, downscale: int) -> Scene:
    """The frame of ``scene`` loaded again at ``downscale`` (as ``scene.downscale`` loads it:
    images area-averaged from the capture's own, intrinsics scaled to match)."""
    config = scene.meta.get("config")
    if config is None:
        raise SceneError(f"scene '{scene.name}' was not loaded by load_scene, so it cannot be loaded at another "
                         "resolution; load it with flamerecon.load_scene")
    return load_scene({**config, "downscale": int(downscale)})


__all__ = ["SCENE_KEYS", "SCENE_LOADERS", "Scene", "SceneError", "capture_frames", "load_downscaled", "load_frame", "load_scene", "register_built_in",
           "register_scene"]
