"""Progress of a long wait (a camera fit, leave-one-out folds, a sweep, a reference solve): a
line per step with the elapsed and the expected remaining time, through the ``logging`` logger
``flamerecon.progress`` at INFO (into train.log and the console under ``train.py``; on stderr
where nothing configured logging, as in the scripts).

``FLAMERECON_PROGRESS=0`` silences it (the test suite does)."""

from __future__ import annotations

import logging
import os
import sys
import time

#: the environment variable that silences progress lines when set to 0
ENV = "FLAMERECON_PROGRESS"

log = logging.getLogger("flamerecon.progress")


def duration(seconds: float) -> str:
    """'8 s', '3 min 20 s', '1 h 05 min'."""
    s = round(max(float(seconds), 0.0))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _emit(message: str) -> None:
    if os.environ.get(ENV, "1") == "0":
        return
    if not logging.getLogger().hasHandlers() and not log.handlers:  # nothing configured logging
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.info(message)


class Progress:
    """``total`` steps of a wait called ``what``: :meth:`update` (or :meth:`step`) logs
    ``what: <unit> done/total (detail); <elapsed> elapsed, about <remaining> left``, at most
    one line per ``every`` seconds except the last; the remaining time assumes the steps left
    take as long as the ones done. With ``after`` > 0 a wait says nothing until it has lasted
    that long (no "started" line, and none at all for a short one): for work that is quick at
    one size and long at another (an assembly, a render)."""

    def __init__(self, what: str, total: int, unit: str = "step", every: float = 0.0, after: float = 0.0) -> None:
        self.what, self.total, self.unit, self.every = what, max(int(total), 1), unit, float(every)
        self.after = float(after)
        self.done = 0
        self.start = self.last = time.perf_counter()
        self.spoken = self.after <= 0
        if self.spoken:
            _emit(f"{what}: {self.total} {unit}{'s' if self.total != 1 else ''}, started")

    def update(self, done: int, detail: str = "") -> None:
        """``done`` steps of :attr:`total` are finished (``detail`` says about the last)."""
        self.done = min(int(done), self.total)
        now = time.perf_counter()
        if not self.spoken:  # quiet until ``after`` seconds, then a line at once
            if now - self.start < self.after:
                return
            self.spoken, self.last = True, now - self.every
        if self.done < self.total and now - self.last < self.every:
            return
        self.last = now
        elapsed = now - self.start
        left = elapsed * (self.total - self.done) / max(self.done, 1)
        about = f"about {duration(left)} left" if self.done < self.total else "done"
        _emit(f"{self.what}: {self.unit} {self.done}/{self.total}" + (f" ({detail})" if detail else "")
              + f"; {duration(elapsed)} elapsed, {about}")

    def step(self, detail: str = "") -> None:
        """One more step finished."""
        self.update(self.done + 1, detail)
