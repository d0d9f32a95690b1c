"""flamerecon: sparse multi-view emission tomography of flames and smoke."""

__version__ = "0.1.0"
