"""A warm-start density (``init=`` a run folder or density.npz on the command line,
``fr.reconstruct(..., init=)`` in Python) is checked when it is read, before any work: NaN, Inf,
negative or absurd values are refused in one line naming the file (or the argument) and what is
wrong, exit status 2; they used to be solved from, reported as divergence with advice about the
step, and written back as "the last good iterate"."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.errors import ArgumentError
from flamerecon.fit import reconstruct as core
from flamerecon.fit.reconstruct import SolveHook
from flamerecon.outputs.export import save_density
from flamerecon.run.runner import run_task
from tests.helpers import tiny_cfg, tiny_synthetic

ERROR = "flamerecon: error: "


def broken(kind: str) -> np.ndarray:
    """The tiny scene's density on a 16-cell grid, with one fault."""
    d = np.full((3, 16, 16, 16), 0.1, np.float32)
    d[0, 8, 8, 8] = {"nan": np.nan, "inf": np.inf, "negative": -0.5, "absurd": 1e30, "huge": 1e4}[kind]
    return d


CASES = {  # fault: what the message says
    "nan": r"holds 1 NaN/Inf values; warm start from a run that finished",
    "inf": r"holds 1 NaN/Inf values",
    "negative": r"holds 1 negative values \(min -0\.5\) where an emission density is >= 0",
    "absurd": r"peaks at 1e\+30: a ray through the box would integrate to about .*no density of this capture",
    "huge": r"peaks at 1e\+04",
}


def no_work(monkeypatch) -> None:
    monkeypatch.setattr(core, "calibrated_scene", lambda *a: pytest.fail("worked before the check"))
    monkeypatch.setattr(SolveHook, "solve", lambda *a, **k: pytest.fail("solved"))


@pytest.mark.parametrize("kind", list(CASES))
def test_a_bad_init_file_is_refused_in_one_line(kind, tmp_path, capsys, monkeypatch):
    scene = tiny_synthetic()
    (tmp_path / "old").mkdir()
    npz = save_density(tmp_path / "old" / "density.npz", broken(kind), scene.bbox_min, scene.bbox_max,
                       scene.views[:4])
    no_work(monkeypatch)
    (tmp_path / "run").mkdir()
    with pytest.raises(SystemExit) as stop:
        run_task(tiny_cfg(f"init={npz.parent}"), tmp_path / "run")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith(ERROR)]
    assert stop.value.code == 2 and len(lines) == 1, lines
    assert re.search(rf"^init: {re.escape(str(npz))}: its density {CASES[kind]}", lines[0][len(ERROR):]), lines[0]


@pytest.mark.parametrize("kind", ["negative", "absurd"])  # NaN and Inf: see test_api_arguments
def test_a_bad_init_tensor_is_refused_by_the_api(kind, monkeypatch):
    scene = tiny_synthetic()
    no_work(monkeypatch)
    with pytest.raises(ArgumentError, match=rf"^reconstruct\.init: .*{CASES[kind]}"):
        fr.reconstruct(scene, fr.ReconstructionOptions(grid=fr.GridOptions(resolution=16), device="cpu"),
                       init=torch.from_numpy(broken(kind)))
