"""Reconstruct a flame: ``python train.py [key=value ...]`` (Hydra; see conf/train.yaml).

Bad input ends in one line naming the file and field (exit status 2; ``debug=true`` for the
traceback); ``resume=RUN_DIR`` continues an interrupted run in its folder.
"""

import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    from flamerecon.runner import run_task

    hc = HydraConfig.get()
    return run_task(cfg, hc.runtime.output_dir, multirun=hc.mode == RunMode.MULTIRUN,
                    overrides=list(hc.overrides.task))


if __name__ == "__main__":
    try:
        main()
    except SystemExit as stop:
        if stop.code == 1:  # Hydra refused the command line (unknown key or group, bad syntax)
            print("flamerecon: error: config: the command line was refused (Hydra's message "
                  "above); python train.py --help lists the config groups, --cfg job the keys",
                  file=sys.stderr)
            raise SystemExit(2) from None
        raise
