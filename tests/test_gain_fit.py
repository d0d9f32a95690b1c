"""photometry.fit_gain: per training camera image = gain * integral + offset, fitted between
solves; a camera recorded 1.3 times brighter than the others is found, and held-out cameras
keep gain 1 and offset 0 in cameras.json."""

from __future__ import annotations

import functools
import json
import math

import pytest
from omegaconf import OmegaConf

from flamerecon.run.pipeline import reconstruct
from flamerecon.scenes import SCENE_LOADERS, register_scene
from flamerecon.scenes.synthetic import load as load_synthetic
from tests.helpers import tiny_config


@functools.lru_cache(maxsize=1)
def eight_cameras():
    return load_synthetic(OmegaConf.create({
        "name": "synthetic", "n_cameras": 8, "width": 48, "height": 36,
        "phantom_resolution": 32, "peak": 0.6}))


if "brighter_camera" not in SCENE_LOADERS:
    @register_scene("brighter_camera")
    def _brighter(cfg):
        """The synthetic flame, 8 cameras at 48x36 (peak 0.6), cam01's image times ``scale``."""
        scene = eight_cameras()
        images = scene.images.clone()
        images[1] *= float(cfg["scale"])
        return type(scene)(**{**scene.__dict__, "images": images})


def fitted(tmp_path, scale: float, *overrides: str) -> list[dict]:
    cfg = tiny_config("scene.name=brighter_camera", f"++scene.scale={scale}", "log.eval_every=0",
                      "photometry.fit_gain=true", *overrides)
    reconstruct(cfg, tmp_path)
    return json.loads((tmp_path / "cameras.json").read_text())["cameras"]


def relative_gain(cams: list[dict], name: str) -> float:
    """The gain of camera ``name`` over the geometric mean of the other training cameras'."""
    others = [c["gain"] for c in cams if c["split"] == "train" and c["name"] != name]
    return next(c["gain"] for c in cams if c["name"] == name) / math.exp(
        sum(map(math.log, others)) / len(others))


@pytest.mark.slow
def test_a_camera_recorded_brighter_gets_that_gain(tmp_path):
    cams = fitted(tmp_path / "ten", 1.3, "photometry.rounds=10")
    assert relative_gain(cams, "cam01") == pytest.approx(1.3, rel=0.03)
    train = [c for c in cams if c["split"] == "train"]
    assert math.exp(sum(math.log(c["gain"]) for c in train) / len(train)) == pytest.approx(1.0, abs=1e-5)
    held = [c for c in cams if c["split"] == "holdout"]
    assert [c["name"] for c in held] == ["cam07"]
    assert (held[0]["gain"], held[0]["offset"]) == (1.0, 0.0)
    # the density absorbs part of the mismatch first: alternating longer gets closer
    one = relative_gain(fitted(tmp_path / "one", 1.3, "photometry.rounds=1"), "cam01")
    assert 1.0 < one < relative_gain(cams, "cam01")


@pytest.mark.slow
def test_consistent_cameras_keep_gains_near_one_and_fitting_is_off_by_default(tmp_path):
    cams = fitted(tmp_path / "fit", 1.0, "photometry.rounds=2")
    assert all(c["gain"] == pytest.approx(1.0, abs=0.05) for c in cams)
    assert all(abs(c["offset"]) < 0.01 for c in cams)
    cfg = tiny_config("scene.name=brighter_camera", "++scene.scale=1.3", "log.eval_every=0")
    metrics = reconstruct(cfg, tmp_path / "off")
    assert "photometry" not in metrics["solver"]
    off = json.loads((tmp_path / "off" / "cameras.json").read_text())["cameras"]
    assert {(c["gain"], c["offset"]) for c in off} == {(1.0, 0.0)}
