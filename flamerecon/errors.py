"""The project's exceptions: bad input and runs that cannot go on.

Every :class:`FlameReconError` carries a one-line message that names the file or config field
at fault and what to try; ``train.py`` prints it without a traceback (unless ``debug=true``)
and exits with the error's :attr:`~FlameReconError.exit_code`.
"""

from __future__ import annotations


class FlameReconError(Exception):
    """Base class: a message for the user, not a bug. Exit status 2 (bad input)."""

    exit_code = 2


class ConfigError(FlameReconError, ValueError):
    """A config value that cannot work (unknown solver, a grid too big for memory, ...)."""


class HullError(FlameReconError):
    """Empty silhouettes or an empty visual hull: nothing left to reconstruct."""


class MemoryBudgetError(ConfigError):
    """The requested grid or operator would not fit in the memory available."""


class ResumeError(FlameReconError):
    """``resume=RUN_DIR`` names no resumable run, or one made with another setup."""


class SolveDiverged(FlameReconError):
    """The solve produced NaN/Inf or diverged; the last good iterate was kept and written."""

    exit_code = 3


class Interrupted(FlameReconError):
    """SIGINT/SIGTERM during the solve; the state was checkpointed (exit status 130)."""

    exit_code = 130


class RunFolderError(FlameReconError, FileNotFoundError):
    """A folder given as a run folder (``resume=``, evaluate) that is not one."""
