"""SIGINT from inside a run's solve, through the run hook's ``watch`` (no monkeypatching)."""

from __future__ import annotations

import os
import signal


def interrupt_at(iteration: int, tag_root: str = ""):
    """A ``watch`` for :func:`flamerecon.run.pipeline.reconstruct` that sends this process a SIGINT
    at solver check ``iteration`` of the solve logged under ``tag_root`` (``""``: the final
    grid, ``level<i>/``: coarse level i, ``refit<r>/``: photometry refit r); the run's handler
    then checkpoints and stops."""

    def watch(stage, it, x, info) -> None:
        if stage.tag_root == tag_root and it == iteration:
            os.kill(os.getpid(), signal.SIGINT)

    return watch
