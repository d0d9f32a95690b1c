"""A run says what it will hold before the work (issue 20: huge images on a tiny grid ran
silently past three minutes): one INFO line with its rays, voxels and memory, and a one-line
refusal (exit status 2) naming the setting to change when the memory it needs is clearly not
there (a grid too large alone keeps its own message, see test_errors). Huge configurations are
tried without their work: the free memory is monkeypatched, a huge image is a view of one value."""

from __future__ import annotations

import logging
import re
from dataclasses import replace

import pytest
import torch
from kornia.geometry.camera import PinholeCamera

from flamerecon.fit import checks, workload
from flamerecon.fit import reconstruct as core
from flamerecon.fit.levels import Level
from flamerecon.fit.options import ReconstructionOptions
from flamerecon.fit.reconstruct import SolveHook
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.run.runner import run_task
from tests.helpers import tiny_cfg, tiny_synthetic

ERROR = "flamerecon: error: "
MiB = 2**20


def free(n_bytes):
    return lambda monkeypatch: monkeypatch.setattr(checks, "available_bytes", lambda device: n_bytes)


def nothing(monkeypatch):
    pass


REFUSED = {  # issue 38 family 2: case -> (overrides, patch, message); the option named is the one at fault
    "projector.max_memory_gb below what the run adds": (["projector.max_memory_gb=3e-4"], nothing, (
        r"^projector\.max_memory_gb: 5 views of 48x36 px on a \d+x16x\d+ grid need about .* more memory while "
        r".* \(a peak of at most .*\), but it allows 314\.6 KiB; raise it \(this machine has .* free\) or shrink")),
    "little memory free: the images and grid": ([], free(200_000), (
        r"^(scene\.downscale|grid\.resolution): 5 views of 48x36 px on a .* grid need about .* more memory while .*, "
        r"but 156\.2 KiB is available on cpu; try .*projector\.max_memory_gb$")),
    "a large grid on small images": (["grid.resolution=64"], free(60 * MiB), (
        r"^grid\.resolution: 5 views of 48x36 px on a 43x64x43 grid need about .* more memory while the (final grid "
        r"is solved|result is scored) .* but 48\.0 MiB is available on cpu; try a larger scene\.downscale")),
    "the camera fit's own grid": (["calibration.refine=pose", "calibration.resolution=160"], free(200 * MiB), (
        r"^calibration\.resolution: .* more memory while the cameras are fitted .* try a coarser camera-fit grid")),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_what_clearly_does_not_fit_is_refused_before_the_work(case, tmp_path, capsys, monkeypatch):
    overrides, patch, message = REFUSED[case]
    patch(monkeypatch)
    monkeypatch.setattr(core, "calibrated_scene", lambda *a: pytest.fail("worked before the estimate"))
    with pytest.raises(SystemExit) as stop:
        run_task(tiny_cfg(*overrides), tmp_path)
    lines = [line[len(ERROR):] for line in capsys.readouterr().err.splitlines() if line.startswith(ERROR)]
    assert stop.value.code == 2 and len(lines) == 1 and re.search(message, lines[0]), lines


TOLD = {  # case: (patch, log level, message)
    "an ordinary run": (nothing, logging.INFO, (r"^estimate: \d.* rays, \d.* voxels, .* ray samples per pass: "
                                               r"a peak of at most .* \(.* held now, .* more while .*\) on cpu$")),
    "a long one": (lambda mp: mp.setattr(workload, "LONG_RUN_SAMPLES", 10.0), logging.WARNING,
                   (r"^a large frame: 5 views of 48x36 px, .* ray samples per pass: the camera fit and each solve take "
                    r"minutes here; scene\.downscale=2 works on 1/4 of the pixels; a ladder \(ladder\.rungs=")),
}


@pytest.mark.parametrize("case", list(TOLD))
def test_the_estimate_is_told_at_the_start(case, monkeypatch, caplog):
    patch, level, message = TOLD[case]
    patch(monkeypatch)
    monkeypatch.setattr(SolveHook, "solve", lambda *a, **k: pytest.fail("solved"))
    caplog.set_level(logging.INFO, logger="flamerecon.fit.workload")
    with pytest.raises(pytest.fail.Exception, match="solved"):
        core.reconstruct(tiny_synthetic(), ReconstructionOptions.from_dict(
            {"grid": {"resolution": 16}, "device": "cpu", "solver": {"name": "fista", "max_iters": 30}}))
    told = [r for r in caplog.records if r.name == "flamerecon.fit.workload"]
    assert told[0].levelno == logging.INFO and told[-1].levelno == level, told
    assert len(told) == (1 if level == logging.INFO else 2) and re.search(message, told[-1].getMessage()), told


def huge(scene, factor: int):
    """``scene`` with images ``factor`` times larger per side, every pixel one stored value."""
    B, C, H, W = scene.images.shape
    K = scene.cameras.intrinsics.clone()
    K[:, :2, :3] *= factor
    cams = PinholeCamera(K, scene.cameras.extrinsics, scene.cameras.height * factor, scene.cameras.width * factor)
    return replace(scene, cameras=cams, images=torch.zeros(1, 1, 1, 1).expand(B, C, H * factor, W * factor),
                   truth=None, truth_grid=None)


@pytest.mark.parametrize(("free_bytes", "refused"), [(64 * 2**30, False), (2 * 2**30, True)])
def test_huge_images_on_a_tiny_grid(free_bytes, refused, monkeypatch, caplog):
    scene = huge(tiny_synthetic(), 100)  # 5 views of 4800x3600 px
    options = ReconstructionOptions.from_dict({"device": "cpu", "solver": {"name": "fista", "max_iters": 100}})
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 8)
    free(free_bytes)(monkeypatch)
    caplog.set_level(logging.INFO, logger="flamerecon.fit.workload")
    if refused:
        with pytest.raises(checks.MemoryBudgetError, match=r"^scene\.downscale: 5 views of 4800x3600 px on a 5x8x5 grid"):
            workload.check_workload(scene, options, grid, torch.device("cpu"))
        return
    found = workload.check_workload(scene, options, grid, torch.device("cpu"))
    assert found.rays > 10**7 and found.voxels < 1000
    assert f"estimate: {found} on cpu" in caplog.text


@pytest.mark.parametrize(("downscale", "field"), [(2, "ladder.rungs"), (None, "grid.levels")])
def test_a_level_that_does_not_fit_is_named_by_its_own_option(downscale, field, monkeypatch):
    """A rung of the ladder (or a grid.levels entry) whose grid needs more than the final
    grid's: the refusal names the option that made it, not grid.resolution."""
    scene = tiny_synthetic()
    options = ReconstructionOptions.from_dict({"device": "cpu", "grid": {"resolution": 16}})
    fine = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 16)
    level = Level(VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, 200), downscale, None)
    free(100 * MiB)(monkeypatch)
    with pytest.raises(checks.MemoryBudgetError, match=rf"^{re.escape(field)}: a 133x200x133 grid .* use a smaller"):
        workload.check_workload(scene, options, fine, torch.device("cpu"), [level])
