"""The ``flamerecon`` command, also ``python train.py``: reconstruct a flame, ``flamerecon
[key=value ...]`` (Hydra; see conf/train.yaml).

Bad input ends in one line naming the file and field (exit status 2; ``debug=true`` for the
traceback); ``resume=RUN_DIR`` continues an interrupted run in its folder. SIGINT, SIGTERM and
SIGHUP end it with one line and exit status 130 from the first line on
(:mod:`flamerecon.interrupt`; Hydra is imported after the handlers are in place).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from flamerecon.interrupt import EXIT_STATUS, finish, install, say, signal_name

if TYPE_CHECKING:  # the console script imports this module before main() installs the handlers
    from omegaconf import DictConfig


def task(cfg: DictConfig) -> float | None:
    """One Hydra job: the run layer in its run folder (returns the held-out PSNR for sweeps)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from flamerecon.run.runner import run_task

    hc = HydraConfig.get()
    overrides = OmegaConf.to_container(hc.overrides.task, resolve=False)  # as typed: ${...} kept
    return run_task(cfg, hc.runtime.output_dir, multirun=hc.mode == RunMode.MULTIRUN,
                    cwd=hc.runtime.cwd, overrides=overrides)


def save_config(cfg: DictConfig, filename: str, output_dir: Path) -> None:
    """Hydra's ``.hydra/*.yaml`` save, whole or not at all (Hydra's own truncates the file on a
    full disk). It runs before the task, where Hydra would print an exception as a refused
    command line: a failed write ends here in the one-line error, exit status 2."""
    from omegaconf import OmegaConf

    from flamerecon.errors import FlameReconError
    from flamerecon.outputs.atomic import atomic_write_text, make_folder

    try:
        atomic_write_text(make_folder(output_dir) / filename, OmegaConf.to_yaml(cfg))
    except FlameReconError as err:
        print(f"flamerecon: error: {err}", file=sys.stderr)
        raise SystemExit(err.exit_code) from None


def hydra_main():
    """Hydra's entry for :func:`task`, with :func:`save_config` as its ``.hydra/`` writer (Hydra
    names the job after this module: ``train``, so ``train.log``)."""
    import hydra
    import hydra.core.utils

    from flamerecon.resources import config_dir

    hydra.core.utils._save_config = save_config  # run_job looks it up in its module at each job
    return hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")(task)()


def main() -> None:
    """The console entry point. Its first act installs the stop-signal handlers
    (:func:`flamerecon.interrupt.install`). Hydra's refusal of a command line (an unknown key or group
    option, a launcher not installed, bad syntax, a config file it cannot read) is one line and
    exit status 2 (:func:`~flamerecon.run.command_line.refusal`), and leaves no folder behind
    (:func:`~flamerecon.run.runner.discard_unused`); so is a stop signal outside a run (while
    Hydra composes the config, or a sweep starts a job), with exit status 130.
    ``HYDRA_FULL_ERROR=1`` set by the user keeps Hydra's own report."""
    install()
    from hydra._internal.utils import get_args_parser
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException
    from yaml import YAMLError

    from flamerecon.run.cli import config_problem
    from flamerecon.run.command_line import refusal
    from flamerecon.run.runner import discard_unused

    own = os.environ.get("HYDRA_FULL_ERROR") == "1"
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises its errors here instead of printing them
    try:
        hydra_main()
    except HydraException as err:
        if own:
            raise
        discard_unused()
        overrides = get_args_parser().parse_known_args()[0].overrides
        print(f"flamerecon: error: {refusal(err, overrides)}", file=sys.stderr)
        raise SystemExit(2) from None
    except (YAMLError, OmegaConfBaseException) as err:  # a config file or interpolation Hydra could not read
        if own:
            raise
        discard_unused()
        print(f"flamerecon: error: {config_problem(err)}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt as stop:
        discard_unused()
        say(f"flamerecon: error: interrupted by {signal_name(stop)} outside a run's work (starting, or between "
            "a sweep's jobs); every run folder written before is complete")
        raise SystemExit(EXIT_STATUS) from None
    except SystemExit as stop:
        if stop.code == 1:  # Hydra refused the command line in a way it did not raise
            discard_unused()
            print("flamerecon: error: config: the command line was refused (Hydra's message "
                  "above); python train.py --help lists the config groups, --cfg job the keys",
                  file=sys.stderr)
            raise SystemExit(2) from None
        if stop.code == 2:
            discard_unused()
        raise
    finally:
        finish()
        if not own:
            os.environ.pop("HYDRA_FULL_ERROR", None)
