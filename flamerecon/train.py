"""The ``flamerecon`` command, also ``python train.py``: reconstruct a flame, ``flamerecon
[key=value ...]`` (Hydra; see conf/train.yaml).

Bad input ends in one line naming the file and field (exit status 2; ``debug=true`` for the
traceback); ``resume=RUN_DIR`` continues an interrupted run in its folder.
"""

from __future__ import annotations

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from .resources import config_dir


def task(cfg: DictConfig) -> float | None:
    """One Hydra job: the run layer in its run folder (returns the held-out PSNR for sweeps)."""
    from .runner import run_task

    hc = HydraConfig.get()
    return run_task(cfg, hc.runtime.output_dir, multirun=hc.mode == RunMode.MULTIRUN,
                    cwd=hc.runtime.cwd)


#: the console entry point; Hydra names the job after this module (``train``, so ``train.log``)
main = hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")(task)
