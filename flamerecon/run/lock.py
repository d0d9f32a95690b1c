"""One writer per run folder: ``RUN_DIR/.lock``, held with ``flock`` while a process writes there.

The kernel drops a ``flock`` when its process ends, however it ends (SIGKILL included), so a
lock left by a dead process never sticks: the next writer takes it over. The file records the
holder's pid, host and start time for the message a refused writer prints. Locks are
re-entrant within one process (the Hydra callback takes the run folder's lock before Hydra writes
``.hydra/`` into it, and the run takes it again), and the file is removed when the last holder
releases it.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from flamerecon.errors import RunFolderInUse, output_error

LOCK_FILE = ".lock"

#: resolved lock path -> (open file descriptor, hold count) of the locks this process holds.
_HELD: dict[Path, list[int]] = {}


def _holder(path: Path) -> str:
    """'pid 123 on host h since 20:01:02' from a lock file, or what is known."""
    try:
        fields = dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)
    except OSError:
        return "another process"
    since = fields.get("since", "")
    return (f"pid {fields.get('pid', '?')} on host {fields.get('host', '?')}"
            + (f" since {since}" if since else ""))


def acquire(run_dir: str | Path) -> Path:
    """Take ``run_dir``'s lock (creating the folder); :class:`~flamerecon.errors.RunFolderInUse`
    when a live process holds it. Returns the lock file's path."""
    folder = Path(run_dir)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise output_error(folder, err) from err
    path = (folder / LOCK_FILE).resolve()
    if path in _HELD:
        _HELD[path][1] += 1
        return path
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise output_error(path, err) from err
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise RunFolderInUse(
                f"{folder}: run folder in use by {_holder(path)} ({path.name} is locked); wait "
                "for that run to end or write into another folder (hydra.run.dir=...)"
            ) from None
        except OSError:  # a file system without flock: the pid in the file decides
            if _alive_holder(path):
                os.close(fd)
                raise RunFolderInUse(
                    f"{folder}: run folder in use by {_holder(path)}; wait for that run to end "
                    f"or write into another folder (or delete {path} if that process is gone)"
                ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:  # else the previous holder removed the file between our open and flock
            break
        os.close(fd)
    record = (f"pid={os.getpid()}\nhost={socket.gethostname()}\n"
              f"since={time.strftime('%Y-%m-%d %H:%M:%S')}\n").encode()
    with contextlib.suppress(OSError):  # only for messages (a full disk may refuse it)
        os.ftruncate(fd, 0)
        os.pwrite(fd, record, 0)
    _HELD[path] = [fd, 1]
    return path


def _alive_holder(path: Path) -> bool:
    """Whether the pid recorded in ``path`` is a live process on this host."""
    try:
        fields = dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)
        pid = int(fields.get("pid", ""))
    except (OSError, ValueError):
        return False
    if fields.get("host") != socket.gethostname():
        return True  # cannot tell: assume it is alive
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return pid != os.getpid()


def release(path: Path) -> None:
    """Give back one hold of the lock at ``path``; the last one removes the file."""
    held = _HELD.get(path)
    if held is None:
        return
    held[1] -= 1
    if held[1] > 0:
        return
    del _HELD[path]
    with contextlib.suppress(OSError):
        path.unlink()
    os.close(held[0])


@contextlib.contextmanager
def run_lock(run_dir: str | Path) -> Iterator[Path]:
    """Hold ``run_dir``'s lock for the duration of the block (see :func:`acquire`)."""
    path = acquire(run_dir)
    try:
        yield path
    finally:
        release(path)


@atexit.register
def _release_all() -> None:
    """At exit (SystemExit included) remove the lock files this process still holds."""
    for path in list(_HELD):
        _HELD[path][1] = 1
        release(path)

