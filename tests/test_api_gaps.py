"""The Python API's own promises (issue 33): ``rec.density`` is one tensor, so an edit in place
reaches ``fr.score``, ``fr.export`` and ``fr.render``; ``fr.render`` is differentiable (its
gradient is the adjoint of the projection, checked against renders of single voxels) and costs
no graph when none is asked for; ``fr.load_run`` refuses a run that failed unless asked."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import flamerecon as fr
from flamerecon.errors import RunFolderError
from tests.helpers import tiny_reconstruction


def _scaled(density):
    density.mul_(2.0)


def _masked(density):
    density[:, :, :, : density.shape[-1] // 2] = 0


def _clamped(density):
    density.clamp_(max=float(density.max()) / 4)


EDITS = {"scaled by 2": _scaled, "half masked out": _masked, "clamped to a quarter of the peak": _clamped}


@pytest.mark.parametrize("edit", list(EDITS))
def test_an_edit_in_place_reaches_score_export_and_render(edit, tmp_path):
    rec = tiny_reconstruction()
    before = rec.density.clone()
    try:
        assert rec.density is rec.density  # one tensor, not a new one each time
        EDITS[edit](rec.density)
        expected = rec.density.clone()
        assert not torch.equal(expected, before)
        fr.export(rec, tmp_path / "flame", "raw")
        raw = np.fromfile(tmp_path / "flame.raw", dtype="<f4").reshape(expected.shape)
        np.testing.assert_array_equal(raw, expected.numpy())
        cams = fr.look_at_camera((0.3, 0.8, 3.0), (0.0, 0.75, 0.0), width=12, height=9)
        assert torch.equal(fr.render(rec.density, rec.grid, cams), fr.render(expected, rec.grid, cams))
        edited = fr.score(rec)["train"]
        rec.density.copy_(before)
        assert edited != fr.score(rec)["train"]
    finally:
        rec.density.copy_(before)


def test_render_is_differentiable_and_its_gradient_is_the_adjoint():
    grid = fr.VoxelGrid.from_box((0, 0, 0), (1, 1, 1), 4)
    cams = fr.look_at_camera((0.3, 0.5, 3.0), (0.5, 0.5, 0.5), width=8, height=6)
    volume = torch.zeros(1, 4, 4, 4, requires_grad=True)  # zero voxels too get their gradient
    weights = torch.rand(1, 1, 6, 8, generator=torch.Generator().manual_seed(0))
    (fr.render(volume, grid, cams) * weights).sum().backward()
    for index in [(0, 1, 2, 1), (0, 2, 2, 2), (0, 3, 0, 3), (0, 0, 0, 0)]:
        unit = torch.zeros(1, 4, 4, 4)
        unit[index] = 1.0
        assert float(volume.grad[index]) == pytest.approx(float((fr.render(unit, grid, cams) * weights).sum()),
                                                          rel=1e-5, abs=1e-7)
    dense = torch.rand(2, 4, 4, 4)
    with_graph = fr.render(dense.clone().requires_grad_(True), grid, cams)
    assert with_graph.requires_grad and torch.allclose(with_graph, fr.render(dense, grid, cams), atol=1e-6)
    assert not fr.render(dense, grid, cams).requires_grad
    with torch.no_grad():
        assert not fr.render(dense.clone().requires_grad_(True), grid, cams).requires_grad


def test_load_run_refuses_a_failed_run_unless_asked(tmp_path):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / "FAILED").write_text("the solve diverged at iteration 7\n")
    (run / "checkpoint.pt").write_text("state")
    with pytest.raises(RunFolderError, match=r"run: the run failed \(the solve diverged at iteration 7\), it did not "
                       r"finish: resume it or run it again \(load_run\(\.\.\., failed=True\)"):
        fr.load_run(run, device="cpu")
    with pytest.raises(RunFolderError, match=r"\.hydra/config\.yaml: not found"):  # asked: read on, as far as it goes
        fr.load_run(run, device="cpu", failed=True)
    with pytest.raises(TypeError, match=r"load_run\.failed: got 'yes'"):
        fr.load_run(run, device="cpu", failed="yes")
