"""How a run ends: the task ``train.py`` runs under Hydra, one-line errors with exit statuses,
``FAILED`` markers, and the failure summary of a multirun.

- A :class:`~flamerecon.errors.FlameReconError` prints ``flamerecon: error: <message>`` on
  stderr, no traceback (``debug=true`` shows it), and exits with the error's status
  (2 bad input, 3 diverged, 130 interrupted).
- A stop signal (SIGINT, SIGTERM, SIGHUP): in the solve, the state is checkpointed and
  ``resume=RUN_DIR`` goes on; anywhere else the run's folder gets a ``FAILED`` saying so (a
  folder holding nothing but Hydra's entries is removed instead); one line, exit status 130.
- Every failed run folder gets a ``FAILED`` file with the message (and the traceback of an
  unexpected exception). Under ``--multirun`` a failed job records it and returns, so the other
  jobs still run; :class:`FailureSummary` lists the failures at the end and exits with status 2.
- An unexpected exception (a bug) is one line too, exit status 2, its traceback in ``FAILED``.
- :class:`LockRunFolder` refuses a second run into a run folder in use.
- A command refused before any work leaves no folder: the run (or sweep) folder it made holds
  only what Hydra wrote there and is removed (:func:`discard_unused`), with the parents it made.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import traceback
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from flamerecon.errors import (
    ConfigError,
    FlameReconError,
    Interrupted,
    ResumeError,
    RunFolderError,
    RunFolderInUse,
    errno_text,
)
from flamerecon.interrupt import EXIT_STATUS, say, signal_name
from flamerecon.outputs.atomic import atomic_write_text
from flamerecon.outputs.sweep import FAILED_FILE, sweep_table, write_sweep_csv
from flamerecon.run.checkpoint import CHECKPOINT_FILE
from flamerecon.run.cli import config_problem, one_line

#: what Hydra (and the lock) put into a run or sweep folder before the run does any work
HYDRA_ENTRIES = frozenset({".hydra", "train.log", "multirun.yaml", ".lock"})
#: run and sweep folders this process made (:class:`LockRunFolder`) -> the topmost folder made
_MADE: dict[Path, Path] = {}


def discard_unused(folder: str | Path | None = None) -> bool:
    """Remove ``folder`` (default: every folder this process made for its run) where this
    process made it and it holds nothing but :data:`HYDRA_ENTRIES`, with the parents made
    along with it; returns whether anything was removed."""
    removed = False
    for made in [Path(folder).absolute()] if folder is not None else list(_MADE):
        top = _MADE.get(made)
        if top is None or not made.is_dir() or any(p.name not in HYDRA_ENTRIES for p in made.iterdir()):
            continue
        shutil.rmtree(made, ignore_errors=True)
        del _MADE[made]
        removed = True
        for parent in made.parents:
            if parent == top.parent:
                break
            try:
                parent.rmdir()  # only an empty one
            except OSError:
                break
    return removed


def record_failure(run_dir: str | Path | None, message: str) -> Path | None:
    """Write ``run_dir/FAILED`` with ``message`` (atomically); None where there is no folder,
    it is gone or cannot be written (the one-line error on stderr says why)."""
    if run_dir is None:
        return None
    folder = Path(run_dir)
    if not folder.is_dir():
        return None
    try:
        return atomic_write_text(folder / FAILED_FILE, message.rstrip() + "\n")
    except OSError:
        return None


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


def config_block(cfg: DictConfig, run_dir: str | Path, overrides: list[str] | None) -> str:
    """The composed config's nodes that set a run apart, as YAML (scene, holdout, device, grid,
    solver, and debias, select and calibration when they are on), with the command line's
    overrides and where the whole config is kept; printed once the run's checks have passed
    (:meth:`~flamerecon.fit.reconstruct.SolveHook.begin`): a refused command prints one line."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    shown = {k: plain[k] for k in ("scene", "holdout", "device", "grid", "solver") if k in plain}
    if (plain.get("debias") or {}).get("method", "none") != "none":
        shown["debias"] = plain["debias"]
    if (plain.get("select") or {}).get("auto"):
        shown["select"] = {k: v for k, v in plain["select"].items() if k != "candidates"}
    if (plain.get("calibration") or {}).get("refine", "none") != "none":
        shown["calibration"] = plain["calibration"]
    text = OmegaConf.to_yaml(OmegaConf.create(shown)).rstrip()
    return (f"config (overrides: {' '.join(overrides or []) or 'none'}; all of it: "
            f"{Path(run_dir) / '.hydra' / 'config.yaml'}, or python train.py --cfg job):\n"
            + "\n".join(f"  {line}" for line in text.splitlines()))


def as_the_command_line_says(cfg: DictConfig, overrides: list[str] | None, run_dir: str | Path) -> tuple[DictConfig, list[str]]:
    """(``cfg``, notes): ``cfg`` as the command line's ``overrides`` mean it, before any work: an option given
    that does nothing in the combination refused (:func:`~flamerecon.fit.option_rules.check_options`
    with the keys given: ``uncertainty.scale=5`` without ``uncertainty.enabled``), and a preset's
    rule that would override an option given dropped (:func:`~flamerecon.run.cli.as_given`;
    ``.hydra/config.yaml`` rewritten to what runs, so that ``resume=`` goes on alike), and a line
    for each rule dropped (printed with the config once the checks have passed)."""
    from flamerecon.fit.option_rules import check_options, given_keys
    from flamerecon.run.cli import as_given

    check_options(OmegaConf.to_container(cfg, resolve=True), given_keys(overrides or []))
    cfg, notes = as_given(cfg, overrides)
    saved = Path(run_dir) / ".hydra" / "config.yaml"
    if notes and saved.is_file():
        atomic_write_text(saved, OmegaConf.to_yaml(cfg))
    return cfg, notes


def run_task(cfg: DictConfig, run_dir: str | Path, multirun: bool = False,
             cwd: str | Path | None = None, overrides: list[str] | None = None) -> float | None:
    """Reconstruct (or resume, with ``resume=RUN_DIR``: the run's own config, with the budget
    ``overrides`` of the command line, see :func:`~flamerecon.run.resume.resume_config`) and print the
    summary; returns the mean held-out PSNR, or None for a multirun job that failed. ``cwd`` is
    the folder the command was started in, against which relative paths resolve (default: the
    working directory).

    A failure writes ``FAILED`` into the folder of the run that failed: the resumed folder once
    its solve went on, this command's own folder (``run_dir``) when the resume was refused, so
    that a finished run's folder never gets one; a folder another process holds gets nothing."""
    from flamerecon.run.pipeline import flat_metrics, reconstruct, run_config, summary_table
    from flamerecon.run.resume import resume_config

    start = Path.cwd() if cwd is None else Path(cwd)
    failed_in = Path(run_dir)
    debug = False
    try:
        resolves(cfg)
        debug = cfg.get("debug", False) is True  # debug=yes is refused by its rule, without a traceback
        if cfg.get("resume"):
            resumed = Path(str(cfg.resume))
            if not resumed.is_absolute():
                resumed = start / resumed
            cfg = resume_config(run_config(resumed), cfg, list(overrides or []), resumed)
            anchor_scene_root(cfg, start)
            metrics = reconstruct(cfg, resumed, resume=True)
            (resumed / FAILED_FILE).unlink(missing_ok=True)
            run_dir = resumed
        else:
            anchor_scene_root(cfg, start)
            cfg, notes = as_the_command_line_says(cfg, overrides, run_dir)
            metrics = reconstruct(cfg, run_dir, announce="\n".join([config_block(cfg, run_dir, overrides), *notes]))
    except FlameReconError as err:
        if debug:
            raise
        say(f"flamerecon: error: {err}")
        if isinstance(err, Interrupted):  # checkpointed: checkpoint.pt is the record
            raise SystemExit(err.exit_code) from None
        unused = err.exit_code == 2 and not cfg.get("resume") and discard_unused(failed_in)
        if not isinstance(err, RunFolderInUse) and not unused:
            record_failure(failure_folder(err, cfg, failed_in), str(err))
        if multirun:
            return None
        raise SystemExit(err.exit_code) from None
    except KeyboardInterrupt as stop:  # a stop signal outside the solve (in it: Interrupted)
        say(f"flamerecon: error: {interrupted(stop, cfg, failed_in)}")
        raise SystemExit(EXIT_STATUS) from None
    except Exception as err:
        if debug:
            raise
        detail = traceback.format_exc()
        folder = failure_folder(err, cfg, failed_in)
        marker = record_failure(folder, f"unexpected {type(err).__name__}: {err}\n\n{detail}")
        folder = folder or failed_in
        if isinstance(err, OSError) and err.errno:  # a system error outside flamerecon's writers
            where = err.filename if err.filename is not None else folder
            message = f"{where}: {errno_text(err)}; check the path, its permissions and free space"
        elif isinstance(err, (OSError, ValueError)):  # bad input said in a library's own words
            message = one_line(err)
        else:
            where = f"the traceback is in {marker}" if marker else "debug=true shows the traceback"
            message = (f"{folder}: unexpected {type(err).__name__}: {one_line(err)}; {where} "
                       "(please report it)")
        print(f"flamerecon: error: {message}", file=sys.stderr)
        if multirun:
            return None
        raise SystemExit(2) from None
    print(f"\nflamerecon: {cfg.scene.name}, run folder {run_dir}\n{summary_table(metrics)}")
    return flat_metrics(metrics)["heldout_psnr"]


def interrupted(stop: KeyboardInterrupt, cfg: DictConfig, own: Path) -> str:
    """The one line for a stop signal outside the solve (or a second one in it, which stops at
    once), after recording it: a folder that holds
    nothing but Hydra's entries is removed (:func:`discard_unused`), any other gets a ``FAILED``
    (a checkpoint it holds is kept: ``resume=`` goes on from it)."""
    folder = failure_folder(stop, cfg, own)
    signal = signal_name(stop)
    if not cfg.get("resume") and discard_unused(own):
        return f"{folder}: interrupted by {signal} before the run wrote anything; its folder was removed"
    if folder is None:
        return f"resume={cfg.resume}: interrupted by {signal} before the run resumed; nothing was changed"
    if (folder / CHECKPOINT_FILE).is_file():
        what = f"its last checkpoint is kept: python train.py resume={folder} goes on from it"
    else:
        what = "nothing was checkpointed: run the command again"
    how = f"stopped at once by a second {signal}" if getattr(stop, "forced", False) else \
        f"interrupted by {signal} outside the solve"
    message = f"{folder}: {how}; {what}"
    record_failure(folder, message)
    return message


def resolves(cfg: DictConfig) -> None:
    """A :class:`~flamerecon.errors.ConfigError` for an interpolation of ``cfg`` that does not
    resolve (:func:`~flamerecon.run.cli.config_problem`), before any work."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        raise ConfigError(config_problem(err)) from None


def failure_folder(err: BaseException, cfg: DictConfig, own: Path) -> Path | None:
    """Where a failure is recorded: ``own`` (this command's folder), or with ``resume=`` the
    resumed folder when it still holds its checkpoint (an unfinished run) and the resume was
    not refused: a finished run's folder never gets a ``FAILED``. None where there is no such
    folder (a refused resume under the command line runs in the resumed folder, not its own)."""
    if not cfg.get("resume"):
        return own
    resumed = Path(str(cfg.resume)).absolute()
    refused = isinstance(err, (ResumeError, RunFolderError))
    if not refused and (resumed / CHECKPOINT_FILE).is_file():
        return resumed
    return None if own.absolute() == resumed else own


def failures(sweep_dir: str | Path) -> list[tuple[Path, str]]:
    """(job folder, first line of its FAILED file) for every failed job under ``sweep_dir``."""
    out = []
    for marker in sorted(Path(sweep_dir).rglob(FAILED_FILE)):
        lines = marker.read_text().splitlines()
        out.append((marker.parent, lines[0] if lines else ""))
    return out


class LockRunFolder(Callback):
    """Hydra callback: take the run folder's lock (the sweep folder's, for a multirun) before
    Hydra writes ``.hydra/`` into it, so that a second run into a folder in use is refused
    before it changes anything there (exit status 2). The folder's name is resolved once and
    kept (``${now:...}`` would otherwise be read again), and the folders it makes are recorded
    for :func:`discard_unused`.

    A folder that holds a previous run (or anything else) is refused too, unless
    ``overwrite=true`` (the previous run's files are removed first, other files stay): a
    finished run is never replaced without a word. With ``resume=RUN_DIR`` the command runs
    in RUN_DIR itself (no folder of its own, no ``.hydra/`` written over the run's), its lock
    taken there. A ``renders/``, ``frames/``, ``.hydra/`` or ``train.log`` that is a symbolic
    link is refused: writes stay inside the run folder."""

    def __init__(self) -> None:
        self.held = None

    def _take(self, config: DictConfig, key: str) -> Path:
        from omegaconf import OmegaConf, open_dict, read_write

        from flamerecon.run.lock import acquire

        folder = str(OmegaConf.select(config, key))
        with read_write(config), open_dict(config):
            OmegaConf.update(config, key, folder)
        path = Path(folder).absolute()
        missing = [p for p in (path, *path.parents) if not p.exists()]
        try:
            self.held = acquire(folder)
        except FlameReconError as err:
            refuse(str(err), err.exit_code)
        if missing:
            _MADE[path] = missing[-1]
        return path

    def _give_back(self) -> None:
        from flamerecon.run.lock import release

        if self.held is not None:
            release(self.held)
            self.held = None

    def _refuse_a_previous_run(self, config: DictConfig, folder: Path, what: str) -> None:
        """Refuse ``folder`` when it holds anything but its lock, unless ``overwrite=true``
        (then the run's files go, :func:`~flamerecon.run.folder.clear_run`)."""
        import logging

        from flamerecon.run.folder import clear_run, run_entries
        from flamerecon.run.lock import LOCK_FILE

        held = sorted(p.name for p in folder.iterdir() if p.name != LOCK_FILE)
        if not held:
            return
        if config.get("overwrite") is True:
            if what == "sweep":
                jobs = [p for p in folder.iterdir() if p.is_dir() and not p.is_symlink() and (p / ".hydra").is_dir()]
                for job in jobs:
                    clear_run(job)
                    with contextlib.suppress(OSError):
                        job.rmdir()
            removed = clear_run(folder)
            logging.getLogger(__name__).warning("overwrite=true: removed the previous %s's %s from %s", what,
                                                ", ".join(removed) or "job folders", folder)
            return
        self._give_back()
        shown = ", ".join(held[:4]) + (", ..." if len(held) > 4 else "")
        key = "hydra.sweep.dir" if what == "sweep" else "hydra.run.dir"
        if run_entries(folder):
            again = (f"continue it with resume={folder}, " if (folder / CHECKPOINT_FILE).is_file() else "")
            refuse(f"{folder}: holds a previous {what} ({shown}); flamerecon does not write over it: write into a "
                   f"new folder ({key}=...), {again}or replace it with overwrite=true")
        refuse(f"{folder}: is not empty ({shown}); write the {what} into a new or empty folder ({key}=...), or "
               "add overwrite=true to write it there anyway (other files are left as they are)")

    @staticmethod
    def _no_links(folder: Path) -> None:
        from flamerecon.run.folder import RUN_SUBFOLDERS

        for name in RUN_SUBFOLDERS:
            if (folder / name).is_symlink():
                refuse(f"{folder / name}: is a symbolic link (to {os.readlink(folder / name)}); flamerecon "
                       "writes only inside the run folder: remove the link, or write the run into another folder")

    @staticmethod
    def _resume_here(config: DictConfig) -> None:
        """``hydra.run.dir`` set to the folder ``resume=`` names, and no ``.hydra/`` written
        (the run's own config stays); a folder that is no run folder is refused first."""
        from omegaconf import open_dict, read_write

        from flamerecon.run.folder import CONFIG_FILE

        folder = Path(os.path.expanduser(str(config.resume))).absolute()
        if not (folder / CONFIG_FILE).is_file():
            refuse(f"resume={config.resume}: {folder / CONFIG_FILE} not found; is {folder} a flamerecon run folder?")
        with read_write(config), open_dict(config):
            config.hydra.run.dir = str(folder)
            config.hydra.output_subdir = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        resume = bool(config.get("resume"))
        if resume:
            self._resume_here(config)
        folder = self._take(config, "hydra.run.dir")
        if not resume:
            self._refuse_a_previous_run(config, folder, "run")
        self._no_links(folder)

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._give_back()

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        folder = self._take(config, "hydra.sweep.dir")
        self._refuse_a_previous_run(config, folder, "sweep")


def refuse(message: str, status: int = 2) -> None:
    """End the command before any work with ``flamerecon: error: message``, leaving no folder
    it made (:func:`discard_unused`)."""
    discard_unused()
    say(f"flamerecon: error: {message}")
    raise SystemExit(status)


class FailureSummary(Callback):
    """Hydra callback: after a multirun, print its jobs side by side (what set each apart, its
    held-out scores; also ``sweep_summary.csv``), then list the jobs that failed and exit with
    status 2."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if sweep_dir.is_dir():
            print(sweep_table(sweep_dir), flush=True)
            try:
                print(f"table: {write_sweep_csv(sweep_dir)}", flush=True)
            except FlameReconError as err:  # a full disk: the table above is printed all the same
                print(f"flamerecon: {err}", file=sys.stderr)
        failed = failures(sweep_dir)
        if not failed:
            return
        jobs = sum(1 for p in sweep_dir.iterdir() if p.is_dir() and (p / ".hydra").is_dir())
        lines = [f"flamerecon: {len(failed)} of {jobs} jobs failed:"]
        lines += [f"  {folder}: {msg}" for folder, msg in failed]
        print("\n".join(lines), file=sys.stderr)
        raise SystemExit(2)
