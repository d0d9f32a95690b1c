"""The solve's watchdog: a solver callback that stops on NaN/Inf or divergence (keeping the last
good iterate), checkpoints every N iterations, and stops cleanly on SIGINT/SIGTERM."""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from flamerecon.run.checkpoint import save_checkpoint
from flamerecon.solvers import Solver

log = logging.getLogger(__name__)


class StopSolve(Exception):
    """Raised from the callback to end a solve early; ``reason`` is 'diverged' or 'interrupted'."""

    def __init__(self, reason: str, iteration: int, detail: str):
        super().__init__(f"{reason} at iteration {iteration}: {detail}")
        self.reason, self.iteration, self.detail = reason, iteration, detail


class StopSignals:
    """While active, the first SIGINT/SIGTERM only sets :attr:`received` (the solve stops at its
    next check, after a checkpoint); a second one interrupts at once (KeyboardInterrupt)."""

    def __init__(self) -> None:
        self.received: str | None = None

    def _handle(self, signum, _frame) -> None:
        if self.received is not None:
            raise KeyboardInterrupt
        self.received = signal.Signals(signum).name  # logged by the guard, not in the handler


@contextlib.contextmanager
def stop_signals() -> Iterator[StopSignals]:
    """Install :class:`StopSignals` for SIGINT and SIGTERM (main thread only), restore after."""
    stop = StopSignals()
    previous = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, stop._handle)
    except ValueError:  # not the main thread: leave the handlers alone
        pass
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class SolveGuard:
    """Callback ``(iteration, x (M, C), info)`` wrapping ``inner`` (the monitor).

    - stops with :class:`StopSolve` ('diverged') when ``x`` or the objective is not finite, or
      the objective exceeds ``divergence_factor`` times ``start_objective``; :attr:`last_good`
      then holds the last iterate that passed, as (iteration, x);
    - writes ``run_dir/checkpoint.pt`` at the first check at least ``every`` iterations after
      the last one (0: never on schedule) and when a stop signal was received, then stops
      with :class:`StopSolve` ('interrupted').
    """

    def __init__(self, solver: Solver, inner: Callable | None, run_dir: str | Path, every: int,
                 divergence_factor: float, start_objective: float, meta: dict,
                 start: tuple[int, torch.Tensor], seconds_before: float = 0.0):
        self.solver, self.inner, self.run_dir = solver, inner, Path(run_dir)
        self.every, self.factor = int(every), float(divergence_factor)
        self.start_objective, self.meta = float(start_objective), meta
        self.last_good = (start[0], start[1].detach().clone())
        self.last_saved = start[0]
        self.seconds_before = seconds_before
        self.started = time.perf_counter()
        self.signals: StopSignals | None = None

    def seconds(self) -> float:
        """Solve time so far, including the runs before a resume."""
        return self.seconds_before + time.perf_counter() - self.started

    def __call__(self, it: int, x: torch.Tensor, info: dict) -> None:
        objective = float(info.get("objective", math.nan))
        if not math.isfinite(objective) or not bool(torch.isfinite(x).all()):
            raise StopSolve("diverged", it, "the iterate or the objective became NaN/Inf")
        if self.factor > 0 and objective > self.factor * max(self.start_objective, 1e-300):
            raise StopSolve(
                "diverged", it, f"the objective {objective:.4g} exceeds {self.factor:g} times its "
                f"starting value {self.start_objective:.4g}",
            )
        self.last_good = (it, x.detach().clone())
        if self.inner is not None:
            self.inner(it, x, info)
        if self.signals is not None and self.signals.received:
            log.warning("%s received: checkpointing and stopping at iteration %d",
                        self.signals.received, it)
            self.checkpoint(it, x)
            raise StopSolve("interrupted", it, f"{self.signals.received} received")
        if self.every > 0 and it - self.last_saved >= self.every:
            self.checkpoint(it, x)

    def checkpoint(self, it: int, x: torch.Tensor) -> Path:
        """Save the solver's state (or ``x`` alone for solvers without :meth:`Solver.state`)."""
        state = self.solver.state()
        exact = state is not None and state.get("iteration") == it
        payload = {
            "state": state if exact else {"iteration": it, "x": x},
            "exact": exact,
            "meta": {**self.meta, "seconds": self.seconds(), "start_objective": self.start_objective},
        }
        path = save_checkpoint(self.run_dir, payload)
        self.last_saved = it
        log.info("checkpoint at iteration %d: %s", it, path)
        return path
