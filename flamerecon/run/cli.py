"""What every script in ``scripts/`` shares: its argument parser and how it ends.

Every script ends like ``train.py``: bad input is one line ``flamerecon: error: <file or
field>: <what>; <what to try>`` on stderr and exit status 2 (``--debug`` shows the traceback),
a diverged solve 3, SIGINT (Ctrl-C), SIGTERM or SIGHUP 130 (each script installs the handlers
on its first line, :func:`flamerecon.interrupt.install`). A bad command line (argparse) gets
the same prefix and status.
``--help`` prints the script's module docstring whole, as written (:func:`script_parser`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from flamerecon.errors import FlameReconError, errno_text, output_error
from flamerecon.interrupt import EXIT_STATUS, finish, say, signal_name
from flamerecon.outputs.atomic import make_folder

#: seconds a script waits for a child it passed a stop signal to (a checkpoint takes a moment)
CHILD_GRACE_S = 60


def one_line(err: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(err).split()) or type(err).__name__


def fail(message: str, status: int = 2) -> int:
    """Print ``flamerecon: error: message`` on stderr (:func:`~flamerecon.interrupt.say`: a
    terminal that is gone costs nothing); returns ``status``."""
    say(f"flamerecon: error: {message}")
    return status


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a ``--debug`` flag and the project's one error line (exit status 2; the
    usage is left to ``--help``)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.add_argument("--debug", action="store_true", help="show the traceback of an error")

    def checked(self, name: str, kind: Callable[[str], object], text: str):
        """``kind(text)`` (an argparse type) for a value that argparse did not read, e.g. a path
        made from another argument; its error ends the script as argument ``name``'s."""
        try:
            return kind(text)
        except argparse.ArgumentTypeError as err:
            self.error(f"argument {name}: {err}")

    def error(self, message: str):
        raise SystemExit(fail(f"{self.prog}: {message}; see {self.prog} --help"))


def script_parser(doc: str, file: str) -> ArgumentParser:
    """The parser of the script ``file`` (its ``__file__``): ``--help`` shows ``doc`` (its module
    docstring) whole, line breaks kept, and errors name the script."""
    return ArgumentParser(prog=Path(file).name, description=doc.strip(),
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def frame_list(text: str) -> list[int]:
    """argparse type: '5,25,45' -> [5, 25, 45] (frame numbers >= 0, at least one)."""
    try:
        frames = [int(f) for f in text.split(",") if f.strip()]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame numbers, got '{text}'") from err
    if not frames or min(frames) < 0:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame numbers >= 0, got '{text}'")
    return frames


def at_least(least: int, most: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer >= ``least`` (and <= ``most`` when given)."""
    want = f"an integer >= {least}" if most is None else f"an integer from {least} to {most}"

    def read(text: str) -> int:
        try:
            number = int(text)
        except ValueError:
            number = None
        if number is None or number < least or (most is not None and number > most):
            raise argparse.ArgumentTypeError(f"got '{text}'; give {want}")
        return number

    read.__name__ = want.removeprefix("an ")
    return read


def output_folder(text: str) -> Path:
    """argparse type of an output folder, checked before any work: made (``mkdir -p``) and
    writable, or the argument's error (read-only, no permission, a file in the way)."""
    folder = Path(text)
    if folder.exists() and not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{folder}: is a file, not a folder; give a folder")
    return _writable(folder, folder)


def output_file(text: str) -> Path:
    """argparse type of an output file, checked before any work: its folder made and writable,
    the file itself not a folder."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{path}: is a folder; give a file name")
    if path.parent.exists() and not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{path.parent}: is a file, not a folder")
    _writable(path.parent, path)
    return path


def _writable(folder: Path, path: Path) -> Path:
    """``path`` once ``folder`` is made and a file could be created in it (tried and removed)."""
    try:
        make_folder(folder)
        fd, probe = tempfile.mkstemp(prefix=".flamerecon-probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except FlameReconError as err:
        raise argparse.ArgumentTypeError(one_line(err)) from None
    except OSError as err:
        raise argparse.ArgumentTypeError(one_line(output_error(path, err))) from None
    return path


def compose_train(overrides: list[str], default_scene: str | None = "scalarflow"):
    """``conf/train.yaml`` composed with train.py ``overrides``, ``scene=<default_scene>`` in
    front unless they choose a scene (the real-capture scripts' default; None: the config's),
    an option they give winning over a preset's rule that would override it (:func:`as_given`)."""
    from hydra import compose, initialize_config_dir

    from flamerecon.resources import config_dir

    if default_scene and not any(o.startswith("scene=") for o in overrides):
        overrides = [f"scene={default_scene}", *overrides]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return as_given(compose(config_name="train", overrides=overrides), overrides)[0]


def as_given(cfg, overrides: list[str] | None):
    """(``cfg``, notes): ``cfg`` with every preset's rule that would override an option the
    command line's ``overrides`` give turned off (:func:`~flamerecon.fit.option_rules.given_wins`:
    with ``solver.max_iters`` given, ScalarFlow's ``ladder.final_iterations`` no longer replaces
    it on the run's own level; with ``solver.l1_rel`` given, a preset's ``select.auto`` no longer
    chooses it), and a line saying so for each (``cfg`` itself when none applies)."""
    from omegaconf import OmegaConf

    from flamerecon.fit.option_rules import YIELDS, given_keys, given_wins, leaves

    flat = leaves(OmegaConf.to_container(cfg, resolve=False))
    turned = given_wins(flat, given_keys(overrides or []))
    if not turned:
        return cfg, []
    cfg = cfg.copy()
    notes = []
    for rule in YIELDS:
        if rule.key in turned:
            off, hit = turned[rule.key]
            OmegaConf.update(cfg, rule.key, off, merge=False)
            notes.append(f"{rule.key}: the preset's {_as_typed(flat[rule.key])} set to {_as_typed(off)}: "
                         f"{hit}={_as_typed(flat[hit])}, given on the command line, wins (the rule {rule.what})")
    return cfg, notes


def _as_typed(value) -> str:
    """A config value as the command line writes it (null, true, false; others as they print)."""
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def run_child(command: list[str]) -> subprocess.CompletedProcess:
    """``subprocess.run(command)`` with its output captured, for a script that starts
    ``train.py`` processes: a stop signal that ends this process is passed on to the child
    (which then checkpoints or writes its ``FAILED``), waited for, then raised here."""
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as child:
        try:
            out, err = child.communicate()
        except KeyboardInterrupt as stop:
            with contextlib.suppress(ProcessLookupError):
                child.send_signal(getattr(signal, signal_name(stop)))
            try:
                child.communicate(timeout=CHILD_GRACE_S)
            except subprocess.TimeoutExpired:
                child.kill()
                child.communicate()
            raise
    return subprocess.CompletedProcess(command, child.returncode, out, err)


def timed_child(command: list[str], what: str) -> float:
    """Wall seconds of one child process (:func:`run_child`, a ``train.py`` run); a
    :class:`~flamerecon.errors.FlameReconError` with its last line when it fails (``what``
    names it: ``train.py on frame 5``)."""
    started = time.perf_counter()
    done = run_child(command)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise FlameReconError(f"{what} failed (exit status {done.returncode}): {last}")
    return time.perf_counter() - started


def run_script(body: Callable[[], int | None], debug: bool = False) -> int:
    """Run a script's ``body`` and return its exit status: 0 (or what it returns), or the
    status of the error it raised, printed as one line (re-raised with ``debug``)."""
    try:
        return int(body() or 0)
    except KeyboardInterrupt as stop:
        return fail(f"interrupted by {signal_name(stop)}; every file written before is complete", EXIT_STATUS)
    except Exception as err:
        if debug:
            raise
        return fail(*describe(err))
    finally:
        finish()


def config_problem(err: BaseException) -> str | None:
    """One line for a config that Hydra or OmegaConf could not read, None for another error: a
    file that is not plain YAML (a Python tag, broken syntax: named with its line), an
    interpolation that does not resolve (``${oc.env:VAR}`` without VAR set, ``${a.key}`` that
    is not there: named by the key that holds it)."""
    import yaml
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(err, yaml.YAMLError):
        mark = getattr(err, "problem_mark", None)
        where = f"{mark.name}:{mark.line + 1}" if mark is not None else "a config file"
        problem = " ".join(str(getattr(err, "problem", None) or err).split())
        return (f"{where}: not plain YAML ({problem}); a config file holds plain values, no Python tags (nothing in "
                "it was run)")
    if not isinstance(err, OmegaConfBaseException):
        return None
    key = getattr(err, "full_key", None) or "config"
    text = one_line(err)
    env = re.search(r"Environment variable '([^']+)' not found", text)
    if env:
        return (f"{key}: ${{oc.env:{env[1]}}}: the environment variable {env[1]} is not set; set it (export "
                f"{env[1]}=...), give the interpolation a default (${{oc.env:{env[1]},DEFAULT}}) or give {key}=...")
    missing = re.search(r"Interpolation key '([^']+)' not found", text)
    if missing:
        return f"{key}: refers to ${{{missing[1]}}}, which is not in the config; give {key}=... a value"
    return f"{key}: {text.split('    full_key')[0].strip()}; give {key}=... a plain value"


def describe(err: Exception) -> tuple[str, int]:
    """(one-line message, exit status) for an exception that ends a script."""
    from hydra.errors import HydraException

    if isinstance(err, FlameReconError):
        return one_line(err), err.exit_code
    problem = config_problem(err)
    if problem is not None:
        return problem, 2
    if isinstance(err, HydraException):
        return f"config: {one_line(err)}", 2
    if isinstance(err, OSError) and err.errno:
        where = err.filename if err.filename is not None else "file"
        return f"{where}: {errno_text(err)}; check the path and its permissions", 2
    if isinstance(err, (OSError, ValueError, ImportError)):  # the scripts' own bad-input errors
        return one_line(err), 2
    message = (f"unexpected {type(err).__name__}: {one_line(err)}; run again with --debug for "
               "the traceback (please report it)")
    return message, 2
