"""Stop signals (SIGINT, SIGTERM, SIGHUP): acted on within seconds wherever they arrive, and
ended with one line and exit status :data:`EXIT_STATUS` (130) whichever it was.

Every entry point (``train.py`` and the ``flamerecon`` command, each script in ``scripts/``)
calls :func:`install` on its first line. From then on a stop signal raises :class:`Stopped`
(a ``KeyboardInterrupt``, so that no ``except Exception`` swallows it) at the next Python
instruction, wherever the process is: the entry point ends it with one line, a ``FAILED`` file
in the run's folder and the lock released. One that escapes to the top (a signal during the
imports) is said in one line too, by the excepthook :func:`install` sets, as is a Python that
lacks a package the project needs (exit status 2).

Inside a solve (:func:`deferred`) the first signal is only recorded, so that the solve's guard
checkpoints it at its next check (``python train.py resume=RUN_DIR`` goes on from there). Long
loops (a solver's iterations, the projector's chunks, the camera fit, leave-one-out folds,
weight selection, scoring) call :func:`check` between chunks: a recorded signal is raised
there as :class:`Stopped`, so a solve whose next check is far away stops within a chunk. A
second signal raises at once.

The Python API installs nothing (in a notebook Ctrl-C stays Python's own KeyboardInterrupt);
:func:`check` then costs one read of a global and never raises.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
from collections.abc import Iterator

#: the exit status of a run or script ended by SIGINT, SIGTERM or SIGHUP (128 + SIGINT, as a
#: shell reports Ctrl-C)
EXIT_STATUS = 130
#: the modules of the packages pyproject.toml declares as dependencies, by import name: one of them
#: missing ends an entry point in one line (:func:`_excepthook`), not in a traceback
REQUIRED = {"torch": "torch", "kornia": "kornia", "numpy": "numpy", "cv2": "opencv-python-headless",
            "hydra": "hydra-core", "omegaconf": "hydra-core", "tensorboard": "tensorboard", "tqdm": "tqdm",
            "numba": "numba"}
#: the signals that stop a run (those of them this platform has)
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class Stopped(KeyboardInterrupt):
    """A stop signal acted on; :attr:`signal` names it (``'SIGTERM'``); :attr:`forced`: a second
    signal inside a solve, which wants the process to stop at once (no checkpoint)."""

    def __init__(self, name: str = "SIGINT", forced: bool = False) -> None:
        super().__init__(f"{name} received")
        self.signal, self.forced = name, forced


_received: str | None = None  # the first stop signal received and not yet acted on
_deferring = 0  # depth of deferred() blocks
_installed = False


def signal_name(err: BaseException) -> str:
    """The signal behind a KeyboardInterrupt (``'SIGINT'`` for Python's own)."""
    return getattr(err, "signal", "SIGINT")


def _handle(signum: int, _frame) -> None:
    global _received
    name = signal.Signals(signum).name
    if _received is None and _deferring:
        _received = name  # the solve's guard checkpoints at its next check, or check() raises
        return
    forced = _received is not None
    _received = None
    raise Stopped(name, forced)


def received() -> str | None:
    """The stop signal recorded inside :func:`deferred` and not yet acted on, or None."""
    return _received


def check() -> None:
    """Raise the recorded stop signal as :class:`Stopped` (no-op when there is none): what a
    long loop calls between chunks. Cheap: one read of a global."""
    global _received
    if _received is not None:
        name, _received = _received, None
        raise Stopped(name)


def _install_handlers() -> dict:
    previous = {}
    try:
        for sig in STOP_SIGNALS:
            previous[sig] = signal.signal(sig, _handle)
    except ValueError:  # not the main thread: signals are the main thread's
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        return {}
    return previous


def install() -> None:
    """Make SIGINT, SIGTERM and SIGHUP raise :class:`Stopped` for the rest of the process, and a
    :class:`Stopped` (or KeyboardInterrupt) nobody caught end in one line and exit status
    :data:`EXIT_STATUS`: an entry point's first line. Idempotent; outside the main thread it
    does nothing."""
    global _installed
    if _installed:
        return
    sys.excepthook = _excepthook
    _installed = bool(_install_handlers())


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A block (a solve under its guard) in which the first stop signal is recorded, not raised:
    :func:`received` tells it, :func:`check` raises it; a second one raises at once. Where no
    entry point installed the handlers (a caller of the run layer in Python), they are
    installed for the block and restored after it. A signal still recorded at the end of the
    block is raised there."""
    global _deferring, _received
    previous = {} if _installed else _install_handlers()
    _deferring += 1
    try:
        yield
    except BaseException:
        if _deferring == 1:
            _received = None  # the block ends in an exception anyway: nothing left to act on
        raise
    finally:
        _deferring -= 1
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if not _deferring:
        check()


def finish() -> None:
    """The entry point's work is over (whichever way it ended): ignore stop signals from here
    on, so that one arriving while the process exits (Python restores the default handlers at
    its very end, where SIGHUP would kill it with status 129) changes nothing."""
    if not _installed:
        return
    with contextlib.suppress(ValueError):
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)


def forget() -> None:
    """Drop a recorded signal (after the caller acted on it without :func:`check`)."""
    global _received
    _received = None


def say(line: str) -> None:
    """Print ``line`` on stderr; when the terminal is gone (SIGHUP from a dropped SSH session:
    EIO, EPIPE) send stdout and stderr to /dev/null instead, so that neither this line nor the
    flush at exit turns into another error."""
    try:
        print(line, file=sys.stderr, flush=True)
        sys.stdout.flush()
    except (OSError, ValueError):
        with contextlib.suppress(OSError):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)


def _excepthook(kind, err, tb) -> None:
    """A KeyboardInterrupt that reached the top (a signal during the imports, before the entry
    point's own handling): one line, the atexit handlers (locks) run, exit status 130. A package
    the project needs missing from this Python (:data:`REQUIRED`): one line naming it and how to
    install it, exit status 2."""
    missing = (getattr(err, "name", None) or "").split(".")[0] if issubclass(kind, ModuleNotFoundError) else ""
    if missing in REQUIRED:
        say(f"flamerecon: error: this Python ({sys.executable}) has no module '{missing}' (package "
            f"{REQUIRED[missing]}), which flamerecon needs; install the project into it (pip install -e . "
            "in the checkout, README) or run the Python of the environment it is installed in")
        os._exit(2)
    if not issubclass(kind, KeyboardInterrupt):
        sys.__excepthook__(kind, err, tb)
        return
    finish()
    say(f"flamerecon: error: interrupted by {signal_name(err)} while starting; nothing was written")
    with contextlib.suppress(BaseException):
        atexit._run_exitfuncs()
    os._exit(EXIT_STATUS)
