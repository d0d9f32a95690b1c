"""The option table covers every key of every config group, accepts every shipped default, and
refuses each kind of bad value with a message that names the key."""

from __future__ import annotations

import math

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flamerecon.errors import ConfigError
from flamerecon.fit.option_rules import RULES, check_options, leaves
from tests.helpers import REPO

GROUPS = sorted(f"{d.name}={f.stem}" for d in (REPO / "conf").iterdir()
                if d.is_dir() and d.name != "hydra" for f in d.glob("*.yaml"))
#: scenes that need a data folder to compose with
ROOTED = {"scene=nerf", "scene=opencv"}


def composed(choice: str) -> dict:
    overrides = [choice, *(["scene.root=/data"] if choice in ROOTED else [])]
    with initialize_config_dir(str(REPO / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    return OmegaConf.to_container(cfg, resolve=True)


def test_every_config_group_is_walked():
    assert {"solver=fista", "solver=tv_scalarflow", "scene=scalarflow", "scene=nerf",
            "export=all"} <= set(GROUPS)


@pytest.mark.parametrize("choice", GROUPS)
def test_every_key_of_every_group_has_a_rule_and_its_default_passes(choice):
    config = composed(choice)
    flat = leaves(config)
    missing = sorted(k for k in flat if k not in RULES)
    assert not missing, f"{choice}: keys without a rule in flamerecon/fit/option_rules.py: {missing}"
    numeric = [k for k, v in flat.items()
               if isinstance(v, (int, float)) and not isinstance(v, bool)]
    assert numeric and all(k in RULES for k in numeric)
    check_options(config)  # the shipped defaults pass their own rules


@pytest.mark.parametrize("choice", GROUPS)
def test_every_numeric_key_refuses_nan_and_a_string(choice):
    config = composed(choice)
    for key, value in leaves(config).items():
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        for bad in (math.nan, str(value), True):
            broken = OmegaConf.create(config)
            OmegaConf.update(broken, key, bad, merge=False)
            with pytest.raises(ConfigError, match=rf"^{key}: got ") as info:
                check_options(OmegaConf.to_container(broken))
            assert "\n" not in str(info.value)
            if isinstance(bad, str):
                assert "quoted on the command line" in str(info.value)


BAD = {  # key: (value, message)
    "projector.step": (-1.0, r"must be >= 0.01"),
    "solver.max_iters": (0, r"must be an integer >= 1"),
    "solver.tol": (math.inf, r"must be >= 0"),
    "hull.margin_voxels": (-2, r"integer >= 0"),
    "threads": (0, r"integer >= 1 or null"),
    "checkpoint.every": (-10, r"integer >= 0"),
    "silhouette.method": ("canny", r"unknown method 'canny'"),
    "scene.channels": (2, r"one of 1, 3, auto"),
    "grid.levels": ([0], r"a list of grid sizes"),
    "grid.level_iters": ([1, -1], r"a list of integers >= 1"),
    "grid.bbox": ([[0, 0], [1, 1]], r"\[\[xmin, ymin, zmin\], \[xmax, ymax, zmax\]\]"),
    "holdout": ({"a": 1}, r"view names or indices"),
    "debug": ("yes", r"true or false"),
}


@pytest.mark.parametrize("key", list(BAD))
def test_bad_values_name_the_key(key):
    value, message = BAD[key]
    config = OmegaConf.create(composed("solver=fista"))
    OmegaConf.update(config, key, value, merge=False)
    with pytest.raises(ConfigError, match=rf"^{key}: .*{message}"):
        check_options(OmegaConf.to_container(config))
