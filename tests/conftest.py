"""Shared tiny fixtures: the repo path, a small synthetic scene and a box grid. The helpers
themselves live in :mod:`tests.helpers`.

Everything here is small on purpose (grids of 8-24 cells, images of 16-64 px) so that the
whole suite runs in a few minutes on two busy CPU cores.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from flamerecon.geometry.grid import VoxelGrid
from tests.helpers import REPO

#: no progress lines from the library and the commands the tests start (tests/test_progress.py
#: turns them on where it reads them)
os.environ["FLAMERECON_PROGRESS"] = "0"

#: the small synthetic scene the hull and synthetic tests share (keys of scenes/synthetic.py).
SMALL_SCENE = {
    "name": "synthetic", "n_cameras": 6, "width": 64, "height": 48,
    "phantom_resolution": 48, "seed": 0, "frame": 0,
}


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def small_scene():
    """The built-in synthetic flame at 6 cameras x 64x48 px from a 48-cell phantom."""
    from flamerecon.scenes import load_scene

    return load_scene(dict(SMALL_SCENE))


@pytest.fixture
def box_grid() -> VoxelGrid:
    """An asymmetric box (1.0 x 1.5 x 0.75) of 8 x 12 x 6 cubic cells of side 0.125, off
    the origin so that a sign or offset error shows."""
    return VoxelGrid.from_box((-0.3, 0.2, 1.0), (0.7, 1.7, 1.75), (8, 12, 6))


@pytest.fixture(scope="session", autouse=True)
def scene_cache(tmp_path_factory):
    """The rendered-scene cache of every test (and of the runs they start) in a folder of this
    session, not the user's ~/.cache: hermetic, and still exercised."""
    import os

    from flamerecon.scenes.cache import ENV_DIR

    before = os.environ.get(ENV_DIR)
    os.environ[ENV_DIR] = str(tmp_path_factory.mktemp("scene-cache"))
    yield os.environ[ENV_DIR]
    if before is None:
        os.environ.pop(ENV_DIR, None)
    else:
        os.environ[ENV_DIR] = before
