"""What the tests share: the checkout's paths, THE tiny configuration, geometry and problem
builders. Tests import helpers from here (``from tests.helpers import ...``), never from another
test module; :mod:`tests.helpers.views` writes captures in each loader's format."""

from .config import FAST, HELDOUT, SMALLER, TINY, TRAIN, VIEWS, CliRun, refused_line, tiny_config
from .geometry import random_hull, random_rays, ring_of_cameras
from .interrupts import interrupt_at
from .mounts import tmpfs
from .paths import REPO, TINY_API_SETUP, python_stdout, repo_env
from .problems import (
           assert_columns_solved_alone_alike,
           assert_resumes_exactly,
           csr,
           objective,
           random_coo,
           sklearn_objective,
           tiny_problem,
)
from .scene import defective, tiny_cfg, tiny_reconstruction, tiny_synthetic

__all__ = ["FAST", "HELDOUT", "REPO", "SMALLER", "TINY", "TINY_API_SETUP", "TRAIN", "VIEWS", "CliRun", "assert_columns_solved_alone_alike", "assert_resumes_exactly", "csr",
           "defective", "interrupt_at", "objective", "python_stdout", "random_coo", "random_hull", "random_rays", "refused_line", "repo_env",
           "ring_of_cameras", "sklearn_objective", "tiny_cfg", "tiny_config", "tiny_problem",
           "tiny_reconstruction", "tiny_synthetic", "tmpfs"]
