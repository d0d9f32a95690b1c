"""Reconstruct a flame: ``python train.py [key=value ...]`` (Hydra; see conf/train.yaml)."""

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float:
    from flamerecon.pipeline import flat_metrics, reconstruct, summary_table

    run_dir = HydraConfig.get().runtime.output_dir
    metrics = reconstruct(cfg, run_dir)
    print(f"\nflamerecon: {cfg.scene.name}, run folder {run_dir}\n{summary_table(metrics)}")
    return flat_metrics(metrics)["heldout_psnr"]


if __name__ == "__main__":
    main()
