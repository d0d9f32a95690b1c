"""What every script in ``scripts/`` shares: its argument parser and how it ends.

Every script ends like ``train.py``: bad input is one line ``flamerecon: error: <file or
field>: <what>; <what to try>`` on stderr and exit status 2 (``--debug`` shows the traceback),
a diverged solve 3, Ctrl-C 130. A bad command line (argparse) gets the same prefix and status.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from flamerecon.errors import FlameReconError, errno_text


def one_line(err: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(err).split()) or type(err).__name__


def fail(message: str, status: int = 2) -> int:
    """Print ``flamerecon: error: message`` on stderr; returns ``status``."""
    print(f"flamerecon: error: {message}", file=sys.stderr)
    return status


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a ``--debug`` flag and the project's error line (exit status 2)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.add_argument("--debug", action="store_true", help="show the traceback of an error")

    def error(self, message: str):
        self.print_usage(sys.stderr)
        raise SystemExit(fail(f"{self.prog}: {message}; see {self.prog} --help"))


def frame_list(text: str) -> list[int]:
    """argparse type: '5,25,45' -> [5, 25, 45]."""
    try:
        return [int(f) for f in text.split(",") if f]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame numbers, got '{text}'") from err


def compose_train(overrides: list[str], default_scene: str = "scalarflow"):
    """``conf/train.yaml`` composed with train.py ``overrides``, ``scene=<default_scene>`` in
    front unless they choose a scene (the real-capture scripts' default)."""
    from hydra import compose, initialize_config_dir

    from flamerecon.resources import config_dir

    if not any(o.startswith("scene=") for o in overrides):
        overrides = [f"scene={default_scene}", *overrides]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def run_script(body: Callable[[], int | None], debug: bool = False) -> int:
    """Run a script's ``body`` and return its exit status: 0 (or what it returns), or the
    status of the error it raised, printed as one line (re-raised with ``debug``)."""
    try:
        return int(body() or 0)
    except KeyboardInterrupt:
        if debug:
            raise
        return fail("interrupted (Ctrl-C); what was written before is complete", 130)
    except Exception as err:
        if debug:
            raise
        return fail(*describe(err))


def describe(err: Exception) -> tuple[str, int]:
    """(one-line message, exit status) for an exception that ends a script."""
    from hydra.errors import HydraException

    if isinstance(err, FlameReconError):
        return one_line(err), err.exit_code
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
