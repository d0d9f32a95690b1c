"""TensorBoard helpers: what a run shows while it solves and when it ends."""

from __future__ import annotations

import sys


def summary_writer_class():
    """torch's SummaryWriter, imported without TensorBoard's optional S3 file system: that
    imports botocore and boto3 when they are installed (0.3-0.5 s of every run's start-up on
    2 cores), and a run folder is local. Other imports of botocore are unaffected."""
    blocked = "botocore" not in sys.modules
    if blocked:
        sys.modules["botocore"] = None  # makes `import botocore...` raise ImportError
    try:
        from torch.utils.tensorboard import SummaryWriter
    finally:
        if blocked:
            del sys.modules["botocore"]
    return SummaryWriter


class RunWriter:
    """A SummaryWriter with the run's conventions (tags ``solve/*``, ``eval/*``, ``images/*``),
    opened at the first entry: a run refused before it logged anything leaves no events file."""

    def __init__(self, log_dir: str):
        self.log_dir = log_dir
        self._writer = None

    @property
    def writer(self):
        if self._writer is None:
            self._writer = summary_writer_class()(log_dir=self.log_dir)
        return self._writer

    def scalars(self, step: int, values: dict[str, float], prefix: str = "solve") -> None:
        for k, v in values.items():
            self.writer.add_scalar(f"{prefix}/{k}", v, step)

    def image(self, tag: str, image, step: int, dataformats: str = "CHW") -> None:
        """Log an image: float (C, H, W) in [0, 1], or uint8 (H, W, 3) with ``dataformats="HWC"``."""
        self.writer.add_image(tag, image, step, dataformats=dataformats)

    def hparams(self, params: dict, metrics: dict[str, float]) -> None:
        clean = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in params.items()}
        self.writer.add_hparams(clean, {f"hparam/{k}": v for k, v in metrics.items()}, run_name=".")

    def close(self) -> None:
        if self._writer is not None:
            self._writer.flush()
            self._writer.close()
