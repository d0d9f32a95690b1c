"""Results that look like runs but mean little are said loudly (issue 20): an empty density
(a penalty that kills everything, a solver that collapsed without its guard firing), saturated
views, float images outside [0, 1], an all-black held-out view (its PSNR undefined: null in
metrics.json with the reason beside it) and a held-out PSNR below the all-black floor. One
table of cases over :func:`result_warnings`; then the same warnings where a user meets them: a
run's log, summary and metrics.json, ``scripts/evaluate.py`` and ``fr.score``."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace

import pytest
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.evaluate.result_warnings import result_warnings
from flamerecon.evaluate.scores import score
from flamerecon.run.runner import run_task
from tests.helpers import tiny_cfg, tiny_synthetic
from tests.helpers.scene import defective


def images_with(change):
    """The tiny scene with its images (B, C, H, W) changed in a copy."""
    def make(scene):
        images = scene.images.clone()
        change(images)
        return replace(scene, images=images)
    return make


def as_is(scene):
    return scene


def saturate(images):
    images[1] = (images[1] * 4).clamp(0, 1)


def black_heldout(images):
    images[4] = 0.0


CASES = {  # case: (scene change, density scale, (l1, l1_rel), {code: message pattern})
    "a good density": (as_is, 1.0, (0.01, 0.01), {}),
    "solver.l1_rel=1 zeroes it": (as_is, 0.0, (1.2, 1.0), {
        "empty_density": r"every voxel is zero.*solver\.l1_rel=1 is at or above 1.*lambda_max .* = 1\.2"}),
    "solver.l1_rel=1e6 zeroes it": (as_is, 0.0, (1.2e6, 1e6), {"empty_density": r"solver\.l1_rel=1e\+06 is at"}),
    "an absolute solver.l1 zeroes it": (as_is, 0.0, (5.0, None), {
        "empty_density": r"solver\.l1=5 \(L1 weight 5\) may be too strong: lower it"}),
    "a weak l1_rel, yet empty": (as_is, 0.0, (0.01, 0.01), {"empty_density": r"solver\.l1_rel=0\.01 .*solver\.lr"}),
    "no penalty, collapsed (a diverged solver)": (as_is, 0.0, (0.0, None), {
        "empty_density": r"no L1 penalty is set, so the solver likely diverged .*solver\.lr\) or solver=fista"}),
    "near zero, not zero": (as_is, 1e-9, (0.01, 0.01), {"empty_density": r"\(peak \d.*e-09; the training renders score [+-]0\.0\d\d dB against"}),
    "a saturated view": (images_with(saturate), 1.0, (0.01, 0.01), {
        "saturated": r"view 'cam01': \d+\.\d% of its pixels are at the maximum value .*holdout="}),
    "float values above 1": (images_with(lambda im: im[2].mul_(1.5)), 1.0, (0.01, 0.01), {
        "image_range": r"view 'cam02': \d+ pixel values outside \[0, 1\] \(min 0, max 1\.\d+\); float images"}),
    "negative float values": (images_with(lambda im: im[0].sub_(0.1)), 1.0, (0.01, 0.01), {
        "image_range": r"view 'cam00': \d+ pixel values outside \[0, 1\] \(min -0\.1"}),
    "an all-black held-out view": (images_with(black_heldout), 1.0, (0.01, 0.01), {
        "black_view": r"held-out view 'cam04' is all black: its PSNRs are undefined \(null in metrics\.json\)"}),
    "a render worse than black": (as_is, 30.0, (0.01, 0.01), {
        "below_black": r"held-out view 'cam04': PSNR -?\d+\.\d\d dB is below the all-black image's \d+\.\d\d dB"}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_meaningless_result_gets_its_warning(case):
    change, scale, (l1, l1_rel), expected = CASES[case]
    scene = change(tiny_synthetic())
    train, holdout = [0, 1, 2, 3], [4]
    density = scene.truth * scale
    metrics, _ = score(scene, density, scene.truth_grid, train, holdout, 0.5)
    found = {w["code"]: w["message"] for w in result_warnings(scene, density, metrics, train + holdout, l1, l1_rel)}
    assert set(found) == set(expected), found
    for code, pattern in expected.items():
        assert re.search(pattern, found[code]), found[code]


def test_a_black_views_psnrs_are_undefined_with_the_reason():
    scene = images_with(black_heldout)(tiny_synthetic())
    metrics, _ = score(scene, scene.truth, scene.truth_grid, [0, 1, 2, 3], [4], 0.5, {"threshold": 0.05})
    held = metrics["heldout"]["cam04"]
    assert held["psnr_undefined"] == "the captured view is all black"
    assert all(math.isnan(v) for k, v in held.items() if k.startswith("psnr_") and k != "psnr_undefined")
    assert math.isnan(held["psnr"]) and math.isfinite(held["ssim"])


def cli(tmp_path, capsys, *overrides):
    """(exit status, stdout, metrics.json) of a tiny run (its config kept as Hydra keeps it)."""
    cfg = tiny_cfg(*overrides)
    try:
        run_task(cfg, tmp_path)
        code = 0
    except SystemExit as stop:
        code = stop.code
    (tmp_path / ".hydra").mkdir()
    OmegaConf.save(cfg, tmp_path / ".hydra" / "config.yaml")
    return code, capsys.readouterr().out, json.loads((tmp_path / "metrics.json").read_text())


def test_a_run_that_zeroes_its_density_says_so_and_which_setting(tmp_path, capsys, caplog):
    code, out, metrics = cli(tmp_path, capsys, "solver.l1_rel=1e6")
    assert code == 0  # a warning, not a failure: the run did what it was told
    assert [w["code"] for w in metrics["warnings"]] == ["empty_density"]
    assert "solver.l1_rel=1e+06 is at or above 1" in metrics["warnings"][0]["message"]
    assert re.search(r"WARNINGS \(1\).*\n  ! empty_density: .*solver\.l1_rel=1e\+06", out), out
    assert any(r.levelname == "WARNING" and "empty_density" in r.getMessage() for r in caplog.records)


def test_a_black_heldout_view_is_undefined_in_the_run_the_script_and_the_api(tmp_path, capsys):
    from tests.test_bad_input import script

    code, out, metrics = cli(tmp_path, capsys, *defective("dark_view"), "holdout=[cam02]")
    assert code == 0
    assert metrics["heldout"]["cam02"]["psnr"] is None  # strict JSON: null, the reason beside it
    assert metrics["heldout"]["cam02"]["psnr_undefined"] == "the captured view is all black"
    assert "held-out PSNR [dB]         undefined (held-out view is black)" in out, out
    assert [w["code"] for w in metrics["warnings"]] == ["black_view"]
    assert script("evaluate").main([str(tmp_path), "--device", "cpu", "--no-native"]) == 0
    out = capsys.readouterr().out
    assert "undefined (held-out view is black)" in out and "! black_view: held-out view 'cam02'" in out, out
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["warnings"] == metrics["warnings"] and "timing" in again
    scored = fr.score(fr.load_run(tmp_path, device="cpu"))
    assert [w["code"] for w in scored["warnings"]] == ["black_view"] and "psnr_black" in scored["heldout"]["cam02"]
