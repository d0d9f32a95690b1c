"""How a run ends: the task ``train.py`` runs under Hydra, one-line errors with exit statuses,
``FAILED`` markers, and the failure summary of a multirun.

- A :class:`~flamerecon.errors.FlameReconError` prints ``flamerecon: error: <message>`` on
  stderr, no traceback (``debug=true`` shows it), and exits with the error's status
  (2 bad input, 3 diverged, 130 interrupted).
- Every failed run folder gets a ``FAILED`` file with the message (and the traceback of an
  unexpected exception). Under ``--multirun`` a failed job records it and returns, so the other
  jobs still run; :class:`FailureSummary` lists the failures at the end and exits with status 1.
"""

from __future__ import annotations

import os
import sys
import traceback
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from .atomic import atomic_write_text
from .errors import FlameReconError, Interrupted

FAILED_FILE = "FAILED"


def record_failure(run_dir: str | Path, message: str) -> Path | None:
    """Write ``run_dir/FAILED`` with ``message`` (atomically); None where the folder is gone."""
    folder = Path(run_dir)
    if not folder.is_dir():
        return None
    return atomic_write_text(folder / FAILED_FILE, message.rstrip() + "\n")


def script_error(err: Exception, debug: bool) -> int:
    """A script's known error as one line on stderr (re-raised with ``debug``); returns the
    exit status."""
    if debug:
        raise err
    print(f"flamerecon: error: {err}", file=sys.stderr)
    return getattr(err, "exit_code", 2)


def anchor_scene_root(cfg: DictConfig, start: str | Path) -> None:
    """Make a relative ``scene.root`` that names something under ``start`` (the folder the
    command was started in; Hydra may have changed the working directory since) absolute, in
    place; other roots are left to :func:`~flamerecon.scenes.calibration.resolve_root`."""
    scene = cfg.get("scene")
    if scene is None or "root" not in scene or OmegaConf.is_missing(scene, "root"):
        return
    root = scene.get("root")
    if root is None or str(root) == "":
        return
    path = Path(os.path.expanduser(str(root)))
    if not path.is_absolute() and (Path(start) / path).exists():
        scene.root = str((Path(start) / path).resolve())


def run_task(cfg: DictConfig, run_dir: str | Path, multirun: bool = False,
             cwd: str | Path | None = None) -> float | None:
    """Reconstruct (or resume, with ``resume=RUN_DIR``) and print the summary; returns the mean
    held-out PSNR, or None for a multirun job that failed. ``cwd`` is the folder the command
    was started in, against which relative paths resolve (default: the working directory)."""
    from .pipeline import flat_metrics, reconstruct, run_config, summary_table

    debug = bool(cfg.get("debug", False))
    start = Path.cwd() if cwd is None else Path(cwd)
    try:
        if cfg.get("resume"):
            run_dir = Path(str(cfg.resume))
            if not run_dir.is_absolute():
                run_dir = start / run_dir
            cfg = run_config(run_dir)
            anchor_scene_root(cfg, start)
            metrics = reconstruct(cfg, run_dir, resume=True)
            (run_dir / FAILED_FILE).unlink(missing_ok=True)
        else:
            anchor_scene_root(cfg, start)
            metrics = reconstruct(cfg, run_dir)
    except FlameReconError as err:
        if debug:
            raise
        message = f"flamerecon: error: {err}"
        print(message, file=sys.stderr)
        if isinstance(err, Interrupted):
            raise SystemExit(err.exit_code) from None
        record_failure(run_dir, str(err))
        if multirun:
            return None
        print("flamerecon: (run again with debug=true for the traceback)", file=sys.stderr)
        raise SystemExit(err.exit_code) from None
    except KeyboardInterrupt:
        if debug:
            raise
        print("flamerecon: interrupted outside the solve; nothing was checkpointed", file=sys.stderr)
        raise SystemExit(130) from None
    except Exception as err:
        if not multirun or debug:
            raise
        detail = traceback.format_exc()
        print(f"flamerecon: error (unexpected {type(err).__name__}): {err}", file=sys.stderr)
        record_failure(run_dir, f"unexpected {type(err).__name__}: {err}\n\n{detail}")
        return None
    print(f"\nflamerecon: {cfg.scene.name}, run folder {run_dir}\n{summary_table(metrics)}")
    return flat_metrics(metrics)["heldout_psnr"]


def failures(sweep_dir: str | Path) -> list[tuple[Path, str]]:
    """(job folder, first line of its FAILED file) for every failed job under ``sweep_dir``."""
    out = []
    for marker in sorted(Path(sweep_dir).rglob(FAILED_FILE)):
        lines = marker.read_text().splitlines()
        out.append((marker.parent, lines[0] if lines else ""))
    return out


class FailureSummary(Callback):
    """Hydra callback: after a multirun, list the jobs that failed and exit with status 1."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        failed = failures(sweep_dir)
        if not failed:
            return
        jobs = sum(1 for p in sweep_dir.iterdir() if p.is_dir() and (p / ".hydra").is_dir())
        lines = [f"flamerecon: {len(failed)} of {jobs} jobs failed:"]
        lines += [f"  {folder}: {msg}" for folder, msg in failed]
        print("\n".join(lines), file=sys.stderr)
        raise SystemExit(1)
