"""Where the package finds its own files: the Hydra configs (shipped inside the installed
package as ``flamerecon/conf``, or a checkout's top-level ``conf/``, one source of truth that
the build maps into the package) and the checkout a package may run from."""

from __future__ import annotations

from pathlib import Path

__version__ = "0.1.0"

PACKAGE = Path(__file__).resolve().parent


def checkout_root() -> Path | None:
    """The repository the package runs from (``pip install -e`` or ``PYTHONPATH``), or None
    for an installed package."""
    root = PACKAGE.parent
    return root if (root / "pyproject.toml").is_file() and (root / "conf").is_dir() else None


def config_dir() -> Path:
    """The folder holding ``train.yaml`` and the config groups."""
    packaged = PACKAGE / "conf"
    if (packaged / "train.yaml").is_file():
        return packaged
    root = checkout_root()
    if root is None:
        raise FileNotFoundError(f"{packaged}: the configs are missing from this installation; "
                                "reinstall flamerecon (pip install .)")
    return root / "conf"
