"""A disk cache for what a scene source renders: named tensors computed from the source's
options, kept under ``$FLAMERECON_CACHE_DIR`` (default ``$XDG_CACHE_HOME/flamerecon``, else
``~/.cache/flamerecon``).

An entry's name hashes the options, the versions of flamerecon, torch and kornia and the source
text of the modules that compute it, so editing the renderer never reuses an old picture.
Entries are written atomically and carry a SHA-256 of their tensors: one that cannot be read,
or whose contents do not match, is recomputed and replaced, never used. Each kind of entry has
its own budget (:data:`MAX_ENTRIES` entries, :data:`MAX_BYTES`), the least recently used going
first, so large entries of one kind never evict another kind's. ``FLAMERECON_CACHE=0`` (or
``off``, ``false``, ``no``) turns the cache off; a cache folder that cannot be written only
costs the time to compute.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from types import ModuleType

import kornia
import torch

from flamerecon.errors import torch_reason
from flamerecon.outputs.atomic import atomic_write_bytes
from flamerecon.resources import __version__

log = logging.getLogger(__name__)

ENV_SWITCH = "FLAMERECON_CACHE"
ENV_DIR = "FLAMERECON_CACHE_DIR"
#: entries kept per kind; the least recently used go first beyond this
MAX_ENTRIES = 32
#: bytes kept per kind (one synthetic default scene is ~18-32 MB); the newest entry always stays
MAX_BYTES = 1 << 30


def cache_home() -> Path:
    """``$FLAMERECON_CACHE_DIR``, else ``$XDG_CACHE_HOME/flamerecon``, else ``~/.cache/flamerecon``
    (whether or not the cache is on)."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "flamerecon"


def cache_dir() -> Path | None:
    """The cache folder, or None when ``FLAMERECON_CACHE`` turns the cache off."""
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "off", "false", "no"):
        return None
    return cache_home()


def entry_key(kind: str, options: dict, code: Iterable[ModuleType]) -> str:
    """Hex SHA-256 naming the entry of ``kind`` for ``options`` (JSON-able) computed by ``code``."""
    h = hashlib.sha256()
    h.update(json.dumps({"kind": kind, "options": options, "flamerecon": __version__,
                         "torch": torch.__version__, "kornia": kornia.__version__},
                        sort_keys=True).encode())
    for module in code:
        h.update(Path(module.__file__).read_bytes())
    return h.hexdigest()


def digest(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)};".encode())
        h.update(t.view(torch.uint8).numpy() if t.numel() else b"")
    return h.hexdigest()


def _read(path: Path, key: str) -> dict[str, torch.Tensor] | None:
    """The tensors of the entry at ``path`` if it is whole and is the entry ``key``, else None."""
    try:
        entry = torch.load(path, map_location="cpu", weights_only=True)
        tensors = entry["tensors"]
        if entry["key"] == key and digest(tensors) == entry["digest"]:
            return tensors
    except FileNotFoundError:
        return None
    except Exception as err:  # noqa: BLE001 - any unreadable entry is recomputed
        log.warning("scene cache: %s is unreadable (%s: %s); computing it again and replacing it", path,
                    type(err).__name__, torch_reason(err, "scene-cache entry"))
        return None
    log.warning("scene cache: %s does not match its contents; computing it again", path)
    return None


def _write(folder: Path, kind: str, path: Path, key: str, tensors: dict[str, torch.Tensor]) -> None:
    buffer = io.BytesIO()
    torch.save({"key": key, "digest": digest(tensors), "tensors": tensors}, buffer)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue())
        evict(folder, kind)
    except Exception as err:  # noqa: BLE001 - the cache is an optimisation, never a failure
        log.warning("scene cache: could not write %s (%s); set %s=0 to stop trying", path, err, ENV_SWITCH)


def evict(folder: Path, kind: str) -> None:
    """Delete the least recently used entries of ``kind`` beyond :data:`MAX_ENTRIES` or
    :data:`MAX_BYTES` (the newest always stays); other kinds' entries are not touched."""
    entries = []
    for p in folder.glob(f"{kind}-{'?' * 32}.pt"):  # this kind only: its 32-hex-digit names
        with contextlib.suppress(FileNotFoundError):  # another process may delete it meanwhile
            info = p.stat()
            entries.append((info.st_mtime, info.st_size, p))
    entries.sort(key=lambda e: e[0], reverse=True)  # newest first
    kept_bytes = 0
    for n, (_, size, p) in enumerate(entries):
        if n == 0 or (n < MAX_ENTRIES and kept_bytes + size <= MAX_BYTES):
            kept_bytes += size
        else:
            p.unlink(missing_ok=True)


def cached(kind: str, options: dict, compute: Callable[[], dict[str, torch.Tensor]],
           code: Iterable[ModuleType]) -> dict[str, torch.Tensor]:
    """``compute()`` (name -> CPU tensor), read from the cache when it holds the entry of
    ``kind`` and ``options`` made by the current ``code`` modules, else computed and stored."""
    folder = cache_dir()
    if folder is None:
        return compute()
    key = entry_key(kind, options, code)
    path = folder / f"{kind}-{key[:32]}.pt"
    found = _read(path, key)
    if found is not None:
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: kept longest
        return found
    tensors = compute()
    _write(folder, kind, path, key, tensors)
    return tensors
