"""The project's exceptions: bad input and runs that cannot go on.

Every :class:`FlameReconError` carries a one-line message that names the file or config field
at fault and what to try; ``train.py`` prints it without a traceback (unless ``debug=true``)
and exits with the error's :attr:`~FlameReconError.exit_code`.
"""

from __future__ import annotations

import errno
import os
import re


class FlameReconError(Exception):
    """Base class: a message for the user, not a bug. Exit status 2 (bad input)."""

    exit_code = 2


class ConfigError(FlameReconError, ValueError):
    """A config value that cannot work (unknown solver, a grid too big for memory, ...)."""


class ArgumentError(ConfigError):
    """An argument of a public function or class (an option too) with a value it cannot take:
    out of range, of the wrong shape, inconsistent with another; the message names the
    argument, what it got and what it wants."""


class ArgumentTypeError(FlameReconError, TypeError):
    """An argument of a public function or class of the wrong type (None where a value is
    needed, a dict where options belong, an int tensor where a float one does); the message
    names the argument, what it got and what it wants."""


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


class OutputError(FlameReconError, OSError):
    """A file or folder that could not be written (disk full, read-only, no permission); the
    message names the path and the errno. Whatever was there before is left as it was."""


class RunFolderInUse(RunFolderError):
    """Another live process writes into the run folder (its lock is held)."""


def errno_text(err: OSError) -> str:
    """``errno 28 ENOSPC: No space left on device`` for an OSError (its message when it has
    no errno)."""
    if not err.errno:
        return str(err)
    name = errno.errorcode.get(err.errno, "?")
    return f"errno {err.errno} {name}: {err.strerror or os.strerror(err.errno)}"


_HINTS = {
    errno.ENOSPC: "free space on that file system or write elsewhere",
    errno.EDQUOT: "free space within your quota or write elsewhere",
    errno.EROFS: "the file system is read-only: write elsewhere",
    errno.EACCES: "make the folder writable or write elsewhere",
    errno.EPERM: "make the folder writable or write elsewhere",
}


def output_error(path, err: OSError) -> OutputError:
    """The :class:`OutputError` for writing ``path`` failing with ``err``, with what to try."""
    hint = _HINTS.get(err.errno, "check the folder and its file system, or write elsewhere")
    out = OutputError(f"{path}: cannot write ({errno_text(err)}); {hint}")
    out.errno = err.errno
    return out


def torch_reason(err: Exception, what: str) -> str:
    """What ``torch.load`` found wrong with a file meant to be a flamerecon ``what`` (checkpoint,
    scene-cache entry), one line, without its advice to load with ``weights_only=False`` (which
    would run whatever code the file holds)."""
    text = str(err)
    if "weights_only" in text:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        kind = "a " + found.group(1) if found else "Python objects"
        return (f"it holds {kind}, not only tensors; not a flamerecon {what} (never load it unsafely: that would "
                "run the code it holds)")
    return " ".join(text.split())
