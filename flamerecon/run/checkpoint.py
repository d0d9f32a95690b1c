"""Solver checkpoints in the run folder: ``checkpoint.pt``, written atomically, read back for
``resume=RUN_DIR``."""

from __future__ import annotations

from pathlib import Path

import torch

from flamerecon.errors import ResumeError, output_error, torch_reason
from flamerecon.outputs.atomic import atomic_path, write_errno

CHECKPOINT_FILE = "checkpoint.pt"


def save_checkpoint(run_dir: str | Path, payload: dict) -> Path:
    """``torch.save`` ``payload`` (tensors moved to the CPU) to ``run_dir/checkpoint.pt``, whole
    or not at all; a failed write (torch reports a full disk as a RuntimeError) is an
    :class:`~flamerecon.errors.OutputError` naming the file and the errno."""
    path = Path(run_dir) / CHECKPOINT_FILE
    try:
        with atomic_path(path) as tmp:
            torch.save(_to_cpu(payload), tmp)
    except RuntimeError as err:
        raise output_error(path, write_errno(path.parent, err)) from err
    return path


def load_checkpoint(run_dir: str | Path) -> dict:
    """The checkpoint of ``run_dir``; ResumeError naming the file when there is none or it is
    unreadable."""
    path = Path(run_dir) / CHECKPOINT_FILE
    if not path.is_file():
        finished = (Path(run_dir) / "metrics.json").is_file()
        raise ResumeError(
            f"{path}: no checkpoint; "
            + ("the run has finished (metrics.json is there), nothing to resume" if finished else
               "the run stopped before its first checkpoint (checkpoint.every), start it again")
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for a damaged archive
        raise ResumeError(f"{path}: unreadable checkpoint ({type(err).__name__}: {torch_reason(err, 'checkpoint')})") from err
    for key in ("state", "meta"):
        if key not in payload:
            raise ResumeError(f"{path}: field '{key}' is missing; not a flamerecon checkpoint")
    return payload


def _to_cpu(obj):
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj
