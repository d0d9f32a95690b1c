"""What native libraries print straight on file descriptor 2 (libpng's ``libpng error``,
ffmpeg's ``moov atom not found``, OpenCV's warnings), kept off the terminal so that a damaged
file ends in the project's one error line only."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 sent to a scratch file for the block (Python's own ``sys.stderr``
    writes are flushed first and go there too); restored afterwards, whatever happens."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to protect
        yield
        return
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
