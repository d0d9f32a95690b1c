"""The one place ``device=auto`` is decided."""

from __future__ import annotations

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
