"""``resume=RUN_DIR`` with other overrides on the command line: the run continues under the
config it was started with; an override that would change its problem is refused (named), one
that only changes its budget is applied and said so, one that changes nothing passes."""

from __future__ import annotations

import logging

from omegaconf import DictConfig, OmegaConf

from flamerecon.errors import ResumeError

log = logging.getLogger(__name__)

#: overrides that change how long the solve may go on, not what it solves.
BUDGET_KEYS = ("solver.max_iters", "solver.max_seconds", "checkpoint.every")
#: overrides about this command, not the run: taken from the command line as they are.
COMMAND_KEYS = ("resume", "debug", "threads", "overwrite")


def override_key(override: str) -> str:
    """The config key an override sets: ``++solver.tol=1`` -> ``solver.tol``, ``solver=adam``
    -> ``solver``, ``~init`` -> ``init``."""
    key = override.split("=", 1)[0].lstrip("~+")
    return key.split("@", 1)[0].replace("/", ".")


def _value(cfg: DictConfig, key: str):
    node = OmegaConf.select(cfg, key, default=None)
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def resume_config(saved: DictConfig, now: DictConfig, overrides: list[str], run_dir) -> DictConfig:
    """The config to resume ``run_dir`` with: ``saved`` (its ``.hydra/config.yaml``) with the
    budget overrides of ``overrides`` (values from ``now``, the command's composed config) and
    this command's :data:`COMMAND_KEYS`; :class:`~flamerecon.errors.ResumeError` naming every
    override that would change the problem."""
    refused, budget = [], {}
    for override in overrides:
        key = override_key(override)
        if key in COMMAND_KEYS or key.startswith("hydra."):
            continue
        then, wanted = _value(saved, key), _value(now, key)
        if then == wanted:
            continue
        if key in BUDGET_KEYS:
            budget[key] = wanted
        else:
            refused.append(override)
    if refused:
        raise ResumeError(
            f"resume={run_dir}: {', '.join(refused)} would change the problem the run was started "
            f"with; resume takes only {', '.join(BUDGET_KEYS)} (the budget): start a new run for a "
            "changed problem, or resume without them"
        )
    cfg = saved.copy()
    for key in COMMAND_KEYS:
        if key in now:
            OmegaConf.update(cfg, key, now[key], force_add=True)
    for key, value in budget.items():
        log.warning("resume: %s %s -> %s (a budget override, taken)", key, _value(saved, key),
                    value)
        OmegaConf.update(cfg, key, value, force_add=True)
    return cfg
