"""Run an entry point (``train.py``, a script) as a user does, with a real stop signal sent to
the process at a chosen stage of its work:

    python tests/helpers/signal_child.py SIGNAL WHERE ENTRY [ARGS...]

``WHERE`` is a trigger, and the signal is sent (``os.kill`` on this very process, handled by
the handlers the entry point installed) the first time it fires:

- ``import:MODULE``: when MODULE starts to be imported (the entry's start-up);
- ``check:FUNCTION[:N]``: at the N-th call (default 1) of ``flamerecon.interrupt.check`` from
  the function named FUNCTION (a loop between its chunks: ``_run`` a solver's iterations,
  ``camera_step`` the camera fit, ``select_weights`` the weight selection, ``leave_one_out``
  its folds, ``score_views`` the scoring);
- ``call:MODULE:ATTRIBUTE[:N]``: at the N-th call of MODULE.ATTRIBUTE (``Class.method`` too),
  replaced before the entry runs;
- ``log:TEXT``: when a log record containing TEXT is emitted.

A trigger ending in ``@SECONDS`` starts a timer instead, which sends the signal that many
seconds later, wherever the process then is (a signal that lands inside a long loop)."""

from __future__ import annotations

import importlib
import logging
import os
import runpy
import signal
import sys
import threading


def fire(sig: int, delay: float | None) -> None:
    if delay is None:
        os.kill(os.getpid(), sig)
    else:
        threading.Timer(delay, os.kill, (os.getpid(), sig)).start()


def counted(original, n: int, sig: int, delay, only=None):
    """``original`` wrapped: fires at its n-th call (of those ``only(frame)`` accepts)."""
    calls = [0]

    def wrapper(*args, **kwargs):
        if only is None or only(sys._getframe(1)):
            calls[0] += 1
            if calls[0] == n:
                fire(sig, delay)
        return original(*args, **kwargs)

    return wrapper


class ImportTrigger:
    """A meta-path finder that fires when ``name`` starts to be imported, then steps aside."""

    def __init__(self, name: str, sig: int, delay) -> None:
        self.name, self.sig, self.delay = name, sig, delay

    def find_spec(self, name, path=None, target=None):
        if name == self.name:
            sys.meta_path.remove(self)
            fire(self.sig, self.delay)


def arm(sig: int, where: str) -> None:
    where, _, after = where.partition("@")
    delay = float(after) if after else None
    kind, _, rest = where.partition(":")
    if kind == "import":
        sys.meta_path.insert(0, ImportTrigger(rest, sig, delay))
    elif kind == "check":
        from flamerecon import interrupt

        name, _, n = rest.partition(":")
        interrupt.check = counted(interrupt.check, int(n or 1), sig, delay, lambda f: f.f_code.co_name == name)
    elif kind == "call":
        module, attribute, *n = rest.split(":")
        owner = importlib.import_module(module)
        *path, leaf = attribute.split(".")
        for part in path:
            owner = getattr(owner, part)
        setattr(owner, leaf, counted(getattr(owner, leaf), int(n[0]) if n else 1, sig, delay))
    elif kind == "log":
        original = logging.Logger.handle
        done = [False]

        def handle(self, record):
            if not done[0] and rest in record.getMessage():
                done[0] = True
                fire(sig, delay)
            return original(self, record)

        logging.Logger.handle = handle
    else:
        raise SystemExit(f"signal_child: unknown trigger {where!r}")


if __name__ == "__main__":
    signal_name, where, entry, *args = sys.argv[1:]
    arm(getattr(signal, signal_name), where)
    sys.argv = [entry, *args]
    sys.path[0] = os.path.dirname(os.path.abspath(entry))  # as python ENTRY sets it
    runpy.run_path(entry, run_name="__main__")
