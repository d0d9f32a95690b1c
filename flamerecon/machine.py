"""What this machine has: its cores, its memory (in all, and free right now on a device), and
byte counts for messages. The upper bounds of the options that size a resource
(:mod:`flamerecon.fit.option_rules`) and the memory checks before any work read it."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import torch

#: share of the free memory one step of a run may plan to use
MEMORY_SHARE = 0.8


def _meminfo_available() -> int | None:
    """``MemAvailable`` from /proc/meminfo in bytes (Linux), or None."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_available() -> int | None:
    """Bytes left under a cgroup v2 memory limit (containers), or None where there is none."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
        return max(int(limit) - used, 0)
    except (OSError, ValueError):
        return None


def _address_space_left() -> int | None:
    """Bytes this process may still map under its address-space limit (``ulimit -v``), or
    None where it has none."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit == resource.RLIM_INFINITY:
            return None
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return max(limit - int(line.split()[1]) * 1024, 0)
    except (ImportError, OSError, ValueError, IndexError):
        return None
    return None


def available_bytes(device: torch.device | str = "cpu") -> int | None:
    """Bytes free for new tensors on ``device``: CUDA's free memory, or on the CPU the smallest
    of the kernel's ``MemAvailable``, a container's cgroup headroom and what this process may
    still map (``ulimit -v``) (``os.sysconf`` free pages where /proc is absent). None where it
    cannot be told."""
    device = torch.device(device)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    found = [v for v in (_meminfo_available(), _cgroup_available(), _address_space_left()) if v is not None]
    if not found:
        try:
            found = [os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")]
        except (ValueError, OSError, AttributeError):
            return None
    return min(found)


def cores() -> int:
    """The CPU cores of this machine (``os.cpu_count``; 1 where it cannot be told)."""
    return os.cpu_count() or 1


def total_bytes() -> int | None:
    """This machine's memory in all (RAM, or a container's cgroup limit when smaller), and the
    largest CUDA device's where torch sees one; None where it cannot be told."""
    found = []
    try:
        found.append(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max" and found:
            found[0] = min(found[0], int(limit))
    except (OSError, ValueError):
        pass
    if torch.cuda.is_available():
        found += [torch.cuda.get_device_properties(i).total_memory for i in range(torch.cuda.device_count())]
    return max(found) if found else None


def resident_bytes() -> int:
    """This process's resident memory now, bytes (``/proc/self/statm``; the peak so far where
    that file is missing)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return int(peak_memory()["resident"] * 2**30)


def peak_memory(device: torch.device | str = "cpu") -> dict[str, float]:
    """The process's peak memory so far, GiB: ``resident`` (the largest resident set, all
    devices' host memory; ``ru_maxrss``) and on CUDA ``device`` (torch's largest allocation)."""
    import resource

    peak = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    out = {"resident": peak * (1 if sys.platform == "darwin" else 1024) / 2**30}  # bytes on macOS, KiB elsewhere
    device = torch.device(device)
    if device.type == "cuda":
        out["device"] = torch.cuda.max_memory_allocated(device) / 2**30
    return out


def format_bytes(n: float) -> str:
    """``1536`` -> ``'1.5 KiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"
