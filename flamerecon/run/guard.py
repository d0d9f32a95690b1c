"""The solve's watchdog: a solver callback that stops on NaN/Inf or divergence (keeping the last
good iterate), checkpoints every N iterations, and stops cleanly on a stop signal (SIGINT,
SIGTERM, SIGHUP; see :mod:`flamerecon.interrupt`)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import torch

from flamerecon import interrupt
from flamerecon.run.checkpoint import save_checkpoint
from flamerecon.solvers import Solver

log = logging.getLogger(__name__)


class StopSolve(Exception):
    """Raised from the callback to end a solve early; ``reason`` is 'diverged' or 'interrupted'."""

    def __init__(self, reason: str, iteration: int, detail: str):
        super().__init__(f"{reason} at iteration {iteration}: {detail}")
        self.reason, self.iteration, self.detail = reason, iteration, detail


class SolveGuard:
    """Callback ``(iteration, x (M, C), info)`` wrapping ``inner`` (the monitor).

    - stops with :class:`StopSolve` ('diverged') when ``x`` or the objective is not finite, or
      the objective exceeds ``divergence_factor`` times ``start_objective``; :attr:`last_good`
      then holds the last iterate that passed, as (iteration, x);
    - writes ``run_dir/checkpoint.pt`` at the first check at least ``every`` iterations after
      the last one (0: never on schedule) and, when a stop signal was recorded
      (:func:`flamerecon.interrupt.received`, the solve runs :func:`~flamerecon.interrupt.deferred`),
      then stops with :class:`StopSolve` ('interrupted').
    """

    def __init__(self, solver: Solver, inner: Callable | None, run_dir: str | Path, every: int,
                 divergence_factor: float, start_objective: float, meta: dict,
                 start: tuple[int, torch.Tensor], seconds_before: float = 0.0):
        self.solver, self.inner, self.run_dir = solver, inner, Path(run_dir)
        self.every, self.factor = int(every), float(divergence_factor)
        self.start_objective, self.meta = float(start_objective), meta
        self.last_good = (start[0], start[1].detach().clone())
        self.last_saved = start[0]
        self.saved_here = start[0] > 0  # only a resumed solve starts past 0: from this solve's checkpoint
        self.seconds_before = seconds_before
        self.started = time.perf_counter()

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
        if interrupt.received():
            self.stop_here(it, x, interrupt.received())
        if self.every > 0 and it - self.last_saved >= self.every:
            self.checkpoint(it, x)

    def stop_here(self, it: int, x: torch.Tensor, name: str) -> None:
        """Checkpoint iteration ``it`` (iterate ``x``) and stop with :class:`StopSolve`
        ('interrupted') for the stop signal ``name``, which is then acted on."""
        log.warning("%s received: checkpointing and stopping at iteration %d", name, it)
        interrupt.forget()
        if not (it == self.last_saved and self.saved_here):  # else checkpoint.pt holds this very state
            self.checkpoint(it, x)
        raise StopSolve("interrupted", it, f"{name} received")

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
        self.last_saved, self.saved_here = it, True
        log.info("checkpoint at iteration %d: %s", it, path)
        return path
