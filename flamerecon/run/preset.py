"""The command line's settings for the Python API: ``conf/train.yaml`` composed with a scene
preset (``conf/scene/<name>.yaml``, its solver group and the rest of its defaults list) and
Hydra overrides by Hydra itself, exactly as ``python train.py scene=<name> <overrides>`` composes
them, turned into the core's typed options (:func:`preset`) and the scene's options
(:func:`scene_preset`). The core never reads Hydra; :mod:`flamerecon.api` exposes these."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from flamerecon.errors import ConfigError
from flamerecon.fit.option_rules import check_options
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.resources import config_dir
from flamerecon.run.cli import compose_train, one_line
from flamerecon.run.config import options_from_config


def scene_presets() -> list[str]:
    """The scene presets of ``conf/scene/`` (``synthetic``, ``scalarflow``, ...)."""
    return sorted(p.stem for p in (config_dir() / "scene").glob("*.yaml"))


def compose(scene: str, overrides: tuple[str, ...] | list[str] = ()) -> DictConfig:
    """``conf/train.yaml`` with ``scene=<scene>`` and ``overrides`` (command-line syntax, e.g.
    ``"solver.max_iters=50"``), checked as the command line checks them; a
    :class:`~flamerecon.errors.ConfigError` names an unknown scene or a bad override."""
    from hydra.errors import HydraException

    if scene not in scene_presets():
        raise ConfigError(f"scene: no preset named {scene!r}; choose one of {scene_presets()}")
    bad = [o for o in overrides if not isinstance(o, str) or o.startswith("scene=")]
    if bad:
        raise ConfigError(f"overrides: {bad[0]!r} is not an override string other than scene=; write them "
                          "as on the command line, e.g. 'solver.max_iters=50'")
    try:
        cfg = compose_train([f"scene={scene}", *overrides])
    except HydraException as err:
        raise ConfigError(f"overrides: {one_line(err)}") from None
    check_options(OmegaConf.to_container(cfg, resolve=True))
    return cfg


def preset(scene: str = "synthetic", *overrides: str) -> ReconstructionOptions:
    """The options ``python train.py scene=<scene> <overrides>`` reconstructs with, e.g.
    ``preset("scalarflow")`` or ``preset("synthetic", "solver=fista", "grid.resolution=48")``."""
    return options_from_config(compose(scene, overrides))


def scene_preset(scene: str, *overrides: str) -> dict:
    """The ``scene:`` node ``python train.py scene=<scene> <overrides>`` loads, as plain Python
    (environment variables resolved; a value left ``???`` becomes None)."""
    node = OmegaConf.to_container(compose(scene, overrides).scene, resolve=True)
    return {k: (None if v == "???" else v) for k, v in node.items()}
