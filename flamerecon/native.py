"""What native libraries print straight on file descriptor 2 (libpng's ``libpng error``,
ffmpeg's ``moov atom not found``, OpenCV's warnings), kept off the terminal so that a damaged
file ends in the project's one error line only."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 sent to the null device for the block (Python's own ``sys.stderr``
    writes are flushed first and go there too); restored afterwards, whatever happens."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to protect
        yield
        return
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    sink = os.open(os.devnull, os.O_WRONLY)  # no file made per image read
    try:
        os.dup2(sink, 2)
        yield
    finally:
        os.close(sink)
        os.dup2(saved, 2)
        os.close(saved)
