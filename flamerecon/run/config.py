"""A composed Hydra config, read once: the core's typed options (the run layer's own keys
left out) and what a run sets up before any work (folder, seed, threads, device)."""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from flamerecon.device import resolve_device, set_threads
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.run.folder import RUN_LAYER_KEYS


def options_from_config(cfg: DictConfig) -> ReconstructionOptions:
    """The core's options of a composed config (the run layer's keys left out)."""
    return ReconstructionOptions.from_dict(OmegaConf.to_container(cfg, resolve=True), ignore=RUN_LAYER_KEYS)



def start_run(cfg: DictConfig, run_dir: str | Path) -> tuple[Path, torch.device]:
    """What every reconstruction does first: the run folder made, the seed and thread count
    set, the device resolved."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(cfg.seed))
    set_threads(cfg.get("threads"))
    return run_dir, resolve_device(cfg.device)
