"""Write files whole or not at all.

Every writer here goes to a temporary name in the destination's own folder (same file system,
so :func:`os.replace` is atomic), flushes and fsyncs it, then renames it over the destination.
A crash or exception mid-write leaves the previous file untouched and no partial file behind
(at worst a hidden ``.<name>.<random>.tmp<suffix>`` sibling if the process is killed outright; it never takes
the destination's name). A system error while writing (disk full, read-only folder) becomes an
:class:`~flamerecon.errors.OutputError` naming the destination and the errno.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from flamerecon.errors import FlameReconError, OutputError, output_error

# Permissions of a newly created file under this process's umask (read once: os.umask can only
# be read by setting it).
_UMASK = os.umask(0o022)
os.umask(_UMASK)
_FILE_MODE = 0o666 & ~_UMASK
_TEMP_MARK = ".tmp"
# ".<destination name>.<8 random characters from mkstemp>.tmp<destination suffix>"
_TEMP_NAME = re.compile(r"^\.(?P<dest>.+)\.[a-z0-9_]{8}\.tmp(?P<suffix>\.[^.]+)?$")


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path``, on error it goes.

    The temporary name keeps ``path``'s suffix by default, because some writers (numpy's
    ``savez``, OpenCV's ``imwrite``, VTK) choose the format or append an extension by suffix.
    The caller writes a complete file at the yielded path; the parent folder must exist.

    >>> with atomic_path("out/volume.vti") as tmp:
    ...     writer.SetFileName(str(tmp)); writer.Write()
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"cannot write {dest}: folder {folder} does not exist")
    try:
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{dest.name}.", suffix=_TEMP_MARK + (dest.suffix if suffix is None else suffix),
            dir=folder,
        )
    except OSError as err:
        raise output_error(dest, err) from err
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        _commit(tmp, dest)
    except BaseException as err:
        full = isinstance(err, (OSError, RuntimeError)) and disk_full(folder)  # before the unlink
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(err, FlameReconError):
            raise
        if isinstance(err, OSError) and err.errno:
            raise output_error(dest, err) from err
        if full:  # a writer that reports a full disk without an errno (numpy, torch, VTK)
            raise output_error(dest, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) from err
        raise


def _commit(tmp: Path, dest: Path) -> None:
    """Make the complete temporary ``tmp`` durable and rename it over ``dest``: the one step
    every file written here passes (the disk-full tests fail it on purpose)."""
    if not tmp.exists():
        raise FileNotFoundError(f"writer produced no file at {tmp} for {dest}")
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.chmod(tmp, _FILE_MODE)  # mkstemp makes 0600; give the usual permissions of a new file
    os.replace(tmp, dest)
    _fsync_dir(dest.parent if str(dest.parent) else Path("."))


def make_folder(path: str | os.PathLike) -> Path:
    """``mkdir -p path``; an :class:`~flamerecon.errors.OutputError` naming it when that fails."""
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise output_error(folder, err) from err
    return folder


def make_subfolder(root: str | os.PathLike, name: str) -> Path:
    """``root/name`` made as a folder inside ``root`` (a run folder): an
    :class:`~flamerecon.errors.OutputError` when it is a symbolic link (writing through it would
    replace files outside ``root``) or a file."""
    folder = Path(root) / name
    if folder.is_symlink():
        raise OutputError(f"{folder}: is a symbolic link (to {os.readlink(folder)}); flamerecon writes only "
                          f"inside the run folder: remove the link (or write the run elsewhere)")
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: is a file where flamerecon writes a folder; move it away")
    return make_folder(folder)


def disk_full(folder: str | os.PathLike, min_free: int = 1 << 20) -> bool:
    """Whether ``folder``'s file system has less than ``min_free`` bytes left for us."""
    try:
        stat = os.statvfs(folder)
    except OSError:
        return False
    return stat.f_bavail * stat.f_frsize < min_free


def write_errno(folder: str | os.PathLike, err: Exception) -> OSError:
    """An OSError for a writer that failed without one (``torch.save``'s RuntimeError):
    ENOSPC when ``folder``'s file system is full (:func:`disk_full`), else EIO carrying the
    writer's message."""
    if disk_full(folder):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return OSError(errno.EIO, f"{os.strerror(errno.EIO)} ({err})")


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    return atomic_write_bytes(path, text.encode(encoding))


def atomic_append_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Append ``text`` to the file at ``path`` (a log of rows) by writing the whole file again
    atomically: a failed append leaves the rows before it, never half a row."""
    path = Path(path)
    try:
        old = path.read_bytes()
    except FileNotFoundError:
        old = b""
    except OSError as err:
        raise output_error(path, err) from err
    return atomic_write_bytes(path, old + text.encode(encoding))


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    """Serialise ``obj`` as strict JSON (numpy scalars and arrays converted; a NaN or infinite
    number becomes null, which every JSON reader accepts) and write it atomically."""
    text = json.dumps(finite(obj), indent=indent, allow_nan=False) + "\n"
    return atomic_write_text(path, text)


def update_json_atomic(path: str | os.PathLike, changes: dict) -> dict:
    """Replace the top-level fields ``changes`` names in the JSON object at ``path`` and keep
    every other field (what another tool wrote there), atomically; returns the merged object.
    A missing or unreadable file is written with ``changes`` alone."""
    path = Path(path)
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        old = {}
    merged = {**(old if isinstance(old, dict) else {}), **changes}
    write_json_atomic(path, merged)
    return merged


def finite(obj: Any) -> Any:
    """``obj`` as plain JSON values: numpy and torch values converted, NaN and infinities None."""
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (str, int)):
        return obj
    return finite(_json_default(obj))


def save_npz_atomic(path: str | os.PathLike, compressed: bool = False, **arrays: Any) -> Path:
    """``numpy.savez`` (or ``savez_compressed``) of ``arrays`` to ``path``, atomically.

    ``path`` should end in ``.npz``; numpy would otherwise append it and the file would land
    under a different name than the one replaced.
    """
    dest = Path(path)
    if dest.suffix != ".npz":
        raise ValueError(f"{dest}: an npz archive must be named *.npz")
    save = np.savez_compressed if compressed else np.savez
    # A file object (not a name) stops numpy from appending ".npz" to the temporary name.
    with atomic_path(dest) as tmp, open(tmp, "wb") as fh:
        save(fh, **arrays)
    return dest


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    try:  # torch tensors without importing torch here
        return value.tolist()
    except AttributeError:
        raise TypeError(f"cannot write {type(value).__name__} to JSON") from None


def is_temporary(path: Path) -> bool:
    """Whether ``path`` is named as :func:`atomic_path`'s temporary files are."""
    match = _TEMP_NAME.match(path.name)
    return bool(match) and (match["suffix"] or "") == Path(match["dest"]).suffix


def stale_temporaries(folder: str | os.PathLike, min_age_s: float = 60.0) -> list[Path]:
    """Temporary files that :func:`atomic_path` left in ``folder`` when its process was killed
    outright (SIGKILL, power loss), untouched for at least ``min_age_s`` seconds so that a
    writer still at work is not listed."""
    now = time.time()
    found = []
    for entry in Path(folder).iterdir():
        if not (is_temporary(entry) and entry.is_file()):
            continue
        if now - entry.stat().st_mtime >= min_age_s:
            found.append(entry)
    return sorted(found)
