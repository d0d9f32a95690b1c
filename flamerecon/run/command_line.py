"""A command line Hydra refused, said in one line: a misspelt key gets ``did you mean``, an
unknown config-group option its closest choice, a launcher of a missing extra the ``pip``
command that installs it (see :func:`refusal`)."""

from __future__ import annotations

import difflib

from hydra.errors import ConfigCompositionException, HydraException, MissingConfigException
from omegaconf import DictConfig, OmegaConf

from flamerecon.run.cli import one_line

#: Hydra launchers the ``[sweep]`` extra installs (``slurm`` is conf/hydra/launcher/slurm.yaml,
#: built on ``submitit_slurm``)
SWEEP_LAUNCHERS = ("joblib", "submitit_local", "submitit_slurm", "slurm")
SWEEP_HINT = 'pip install -e ".[sweep]" in the checkout (or pip install "flamerecon[sweep]")'


def refusal(err: HydraException, overrides: list[str]) -> str:
    """The one-line message (without the ``flamerecon: error:`` prefix) for Hydra's refusal
    ``err`` of the command line ``overrides`` (``key=value`` items, as typed)."""
    if isinstance(err, MissingConfigException):
        missing = str(err.missing_cfg_file or "")
        group, _, name = missing.rpartition("/")
        if group == "hydra/launcher" and name in SWEEP_LAUNCHERS:
            return f"hydra/launcher={_choice(overrides, group) or name}: that launcher is not installed; {SWEEP_HINT}"
        if group and err.options:
            close = difflib.get_close_matches(name, list(err.options), n=1)
            hint = f"did you mean {close[0]}?" if close else f"one of {', '.join(err.options)}"
            return f"{group}={name}: no such option; {hint}"
    key = getattr(err.__cause__, "full_key", None)
    if isinstance(err, ConfigCompositionException) and key:
        known = config_keys(_composed(overrides))
        leaf = str(key).rsplit(".", 1)[-1]
        placed = [k for k in known if k.rsplit(".", 1)[-1] == leaf and k != str(key)]  # the option, elsewhere
        close = placed[:2] or difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
        hint = f"did you mean {' or '.join(close)}?" if close else "python train.py --cfg job lists the options"
        return f"{key}: no such option; {hint}"
    return f"config: {one_line(err)}; python train.py --help lists the config groups, --cfg job the keys"


def config_keys(cfg: DictConfig, prefix: str = "") -> list[str]:
    """Every dotted key of ``cfg``, nodes and leaves (``solver``, ``solver.l1``, ...)."""
    keys = []
    for name in cfg:
        path = f"{prefix}{name}"
        keys.append(path)
        child = cfg._get_node(name)
        if isinstance(child, DictConfig) and not child._is_none() and not child._is_missing():
            keys += config_keys(child, f"{path}.")
    return keys


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def _choice(overrides: list[str], group: str) -> str | None:
    """The option ``overrides`` choose for config ``group`` (``hydra/launcher=joblib``)."""
    found = [o.split("=", 1)[1] for o in overrides if "=" in o and _key(o) == group]
    return found[-1] if found else None


def _composed(overrides: list[str]) -> DictConfig:
    """conf/train.yaml with those of ``overrides`` that compose (plain ``key=value`` ones; a
    sweep's or a misspelt key's dropped), Hydra's own node included."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from flamerecon.resources import config_dir

    keep = [o for o in overrides if "=" in o and "," not in o.split("=", 1)[1]]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            for _ in range(len(keep) + 1):
                try:
                    return compose(config_name="train", overrides=keep, return_hydra_config=True)
                except HydraException as err:
                    bad = getattr(err.__cause__, "full_key", None)
                    rest = [o for o in keep if _key(o) != bad] if bad else []
                    keep = rest if len(rest) < len(keep) else []
            return OmegaConf.create({})
    finally:
        GlobalHydra.instance().clear()
