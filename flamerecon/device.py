"""The one place ``device=auto`` and the default CPU thread count are decided."""

from __future__ import annotations

import functools
import math
import os
import statistics
import time

import torch

from flamerecon.errors import ArgumentError
from flamerecon.machine import cores


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
    """Threads for ``cores`` usable cores when other processes keep ``load`` of them busy
    (rounded): the rest, at least 1."""
    return max(1, cores - math.floor(load + 0.5))


def runnable_threads() -> int | None:
    """Threads of the whole machine runnable at this instant, this one included (the 4th field
    of /proc/loadavg); None where the file is missing (not Linux)."""
    try:
        with open("/proc/loadavg") as f:
            return int(f.read().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):
        return None


def busy_cores(reads: int = 5, pause: float = 0.01) -> float:
    """Cores other processes keep busy now: the runnable threads less this one, the median of
    ``reads`` reads ``pause`` seconds apart; without /proc/loadavg the 1-minute load average.
    The load average lags: a run started right after another (a user's previous run, ended
    seconds ago) read about 1 on an idle 2-core machine and took one thread of two."""
    counts = []
    for k in range(reads):
        n = runnable_threads()
        if n is None:
            return os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
        counts.append(max(0, n - 1))
        if k < reads - 1:
            time.sleep(pause)
    return float(statistics.median(counts))


@functools.cache
def default_threads() -> int:
    """:func:`free_cores` of this process's CPU affinity and :func:`busy_cores`, read once per
    process (before its own solves add to the load)."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores()
    return free_cores(usable, busy_cores())


def set_threads(threads: int | None, field: str = "threads") -> int:
    """Set torch's CPU threads: ``threads`` (at most this machine's cores: torch would start as
    many, until other processes cannot fork; ArgumentError naming ``field``), or for None
    :func:`default_threads`; returns the number set. Called at every solve's start, so it holds
    however torch was imported."""
    if threads and int(threads) > cores():
        raise ArgumentError(f"{field}: got {threads}; {field} must be at most {cores()} (this machine's cores; "
                            "more threads only fight over them)")
    n = int(threads) if threads else default_threads()
    torch.set_num_threads(n)
    return n
