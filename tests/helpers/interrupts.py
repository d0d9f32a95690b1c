"""Stop signals sent to this process at a chosen stage: from inside a run's solve through the
run hook's ``watch``, at a function's call, or in a loop between its chunks; and the entry
points' handlers installed for a test (:func:`stop_handlers`). ``signal_child.py`` does the
same in a subprocess."""

from __future__ import annotations

import contextlib
import os
import signal


def interrupt_at(iteration: int, tag_root: str = "", sig: int = signal.SIGINT):
    """A ``watch`` for :func:`flamerecon.run.pipeline.reconstruct` that sends this process ``sig``
    at solver check ``iteration`` of the solve logged under ``tag_root`` (``""``: the final
    grid, ``level<i>/``: coarse level i, ``refit<r>/``: photometry refit r); the run's handler
    then checkpoints and stops."""

    def watch(stage, it, x, info) -> None:
        if stage.tag_root == tag_root and it == iteration:
            os.kill(os.getpid(), sig)

    return watch


@contextlib.contextmanager
def stop_handlers():
    """The entry points' stop-signal handlers (:func:`flamerecon.interrupt.install`) in this
    process for the block, then pytest's own back (handlers, excepthook, recorded signal)."""
    import sys

    from flamerecon import interrupt

    saved = {sig: signal.getsignal(sig) for sig in interrupt.STOP_SIGNALS}
    hook, installed = sys.excepthook, interrupt._installed
    interrupt._installed = False
    interrupt.install()
    try:
        yield interrupt
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        sys.excepthook, interrupt._installed = hook, installed
        interrupt.forget()


def signal_on_call(monkeypatch, owner, name: str, sig: int = signal.SIGTERM, nth: int = 1) -> None:
    """Replace ``owner.name`` (a function) by one that sends this process ``sig`` at its
    ``nth`` call, then calls it."""
    original, calls = getattr(owner, name), [0]

    def wrapper(*args, **kwargs):
        calls[0] += 1
        if calls[0] == nth:
            os.kill(os.getpid(), sig)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)


def signal_in_loop(monkeypatch, function: str, sig: int = signal.SIGTERM, nth: int = 1, times: int = 1) -> None:
    """Send this process ``sig`` (``times`` times in a row) at the ``nth`` call of
    :func:`flamerecon.interrupt.check` from the function named ``function`` (a long loop
    between its chunks)."""
    import sys

    from flamerecon import interrupt

    original, calls = interrupt.check, [0]

    def check():
        if sys._getframe(1).f_code.co_name == function:
            calls[0] += 1
            if calls[0] == nth:
                for _ in range(times):
                    os.kill(os.getpid(), sig)
        return original()

    monkeypatch.setattr(interrupt, "check", check)
