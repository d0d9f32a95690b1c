"""The one place ``device=auto`` and the default CPU thread count are decided."""

from __future__ import annotations

import functools
import math
import os

import torch

from flamerecon.errors import ArgumentError


def resolve_device(name: str | torch.device, field: str = "device") -> torch.device:
    """``auto`` -> CUDA when present, else CPU; ``cpu``/``cuda``/``cuda:N`` as asked
    (ArgumentError naming ``field`` for a device that is not there)."""
    name = str(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ArgumentError(f"{field}: '{name}' is not a device ({err}); use auto, cpu or cuda") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ArgumentError(f"{field}: '{name}' was asked for but torch sees no CUDA device; use auto or cpu")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise ArgumentError(f"{field}: '{name}': torch sees only {torch.cuda.device_count()} CUDA device(s)")
    return device


def free_cores(cores: int, load: float) -> int:
    """Threads for ``cores`` usable cores when other processes keep ``load`` of them busy (the
    1-minute load average, rounded): the rest, at least 1."""
    return max(1, cores - math.floor(load + 0.5))


@functools.cache
def default_threads() -> int:
    """:func:`free_cores` of this process's CPU affinity and the load average, read once per
    process (before its own solves add to the load)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return free_cores(cores, os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0)


def set_threads(threads: int | None) -> int:
    """Set torch's CPU threads: ``threads``, or for None :func:`default_threads`; returns the
    number set. Called at every solve's start, so it holds however torch was imported."""
    n = int(threads) if threads else default_threads()
    torch.set_num_threads(n)
    return n
