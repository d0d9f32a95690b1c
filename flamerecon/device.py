"""The one place ``device=auto`` is decided."""

from __future__ import annotations

import torch

from .errors import ConfigError


def resolve_device(name: str | torch.device, field: str = "device") -> torch.device:
    """``auto`` -> CUDA when present, else CPU; ``cpu``/``cuda`` (or ``cuda:N``) as asked."""
    name = str(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"{field}: '{name}' was asked for but torch sees no CUDA device; "
                          f"use {field}=auto or cpu")
    try:
        return torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"{field}: unknown device '{name}'; use auto, cpu or cuda") from err
