"""An option that does nothing in the combination given is refused by name, on the command
line (ConfigError, exit 2) and in the Python API (ArgumentError), from one table (NEEDS)."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.fit.option_rules import NEEDS, check_options, given_keys
from flamerecon.run.cli import compose_train
from flamerecon.run.folder import RUN_LAYER_KEYS
from tests.helpers import tiny_config

#: (overrides, the key refused; None: accepted): each NEEDS entry alone, then with what it needs
CASES = [
    (["select.auto=true", "select.candidates.fista=[]"], "select.auto"),
    (["select.auto=true", "solver=cgls"], "select.auto"),
    (["select.auto=true"], None),  # fista has candidates
    (["calibration.frames=[3,5]", "calibration.refine=pose"], None),
    (["calibration.gauge=similarity"], "calibration.gauge"),
    (["calibration.gauge=similarity", "calibration.refine=pose+intrinsics"], None),
    (["calibration.rig=true", "calibration.frames=[3,5]"], "calibration.rig"),
    (["calibration.rig=true", "calibration.frames=[3,5]", "calibration.refine=pose"], None),
    (["calibration.score_before=true"], "calibration.score_before"),
    (["calibration.score_before=true", "calibration.refine=pose"], None),
    (["grid.level_iters=5"], "grid.level_iters"),
    (["grid.level_iters=[5]", "grid.levels=[8]"], None),
    (["grid.level_iters=null"], None),
    (["solver=tv", "solver.reweight_eps=0.3"], "solver.reweight_eps"),
    (["solver=tv", "solver.reweight=both"], "solver.reweight"),
    (["solver=tv", "solver.reweight=both", "solver.reweight_eps=0.3", "solver.reweight_rounds=2"], None),
    (["solver=tv", "solver.reweight_rounds=1"], None),
    (["temporal.l2=0.1"], "temporal.l2"),
    (["temporal.tv=0.01"], "temporal.tv"),
    (["temporal.motion=shift"], "temporal.motion"),
    (["temporal.max_shift=1"], "temporal.max_shift"),
    (["temporal.tol=1e-3"], "temporal.tol"),
    (["temporal.l2=0.1", "scene.frames=[0,1]"], None),
    (["temporal.l2=0.01"], None),  # the default: nothing changed
    # options a preset may set for their switch: refused where the command line gives them (issue 38)
    (["uncertainty.scale=5"], "uncertainty.scale"),
    (["uncertainty.scale=5", "uncertainty.enabled=true"], None),
    (["uncertainty.enabled=false", "uncertainty.members=weights"], "uncertainty.members"),
    (["uncertainty.shift_voxels=0.5"], "uncertainty.shift_voxels"),
    (["uncertainty.iterations=10"], "uncertainty.iterations"),
    (["uncertainty.weight_factor=3"], "uncertainty.weight_factor"),
    (["ladder.final_iterations=50"], "ladder.final_iterations"),
    (["ladder.iterations=5", "ladder.rungs=[[2,8]]", "scene.downscale=2"], "ladder.iterations"),  # no rung runs
    (["ladder.iterations=5", "ladder.rungs=[[2,8]]"], None),  # the scene's own downscale is 1: [2, 8] runs
    (["ladder.final_iterations=5", "ladder.rungs=[[4,8]]", "scene.downscale=2"], None),
    (["photometry.rounds=3"], "photometry.rounds"),
    (["photometry.fit_offset=false"], "photometry.fit_offset"),
    (["photometry.rounds=3", "photometry.fit_gain=true"], None),
    (["debias.iterations=20"], "debias.iterations"),
    (["debias.iterations=20", "debias.method=refit"], None),
    (["select.folds=3"], "select.folds"),
    (["select.iterations=10"], "select.iterations"),
    (["select.folds=3", "select.auto=true"], None),
    (["calibration.frames=[3,5]"], "calibration.frames"),
    (["calibration.resolution=8"], "calibration.resolution"),
    *[([f"calibration.{key}={value}"], f"calibration.{key}")
      for key, value in {"rounds": 2, "iterations": 2, "band_px": 2, "max_rays": 100, "prior_rotation_deg": 2.0,
                         "prior_translation": 0.1, "prior_focal": 0.1, "prior_principal_px": 2.0,
                         "fit_against": "others", "first_iterations": 5, "solve_iterations": 5,
                         "seed": 1, "min_gain": 0.1}.items()],
    (["calibration.resolution=8", "calibration.refine=pose"], None),
    (["calibration.offsets=true"], "calibration.offsets"),
    (["calibration.offsets=true", "calibration.refine=pose"], "calibration.offsets"),  # a fit on the frame itself
    (["calibration.offsets=true", "calibration.refine=pose", "calibration.frames=[1,2]"], None),
    (["export.iso=0.2"], "export.iso"),
    (["export.iso=0.2", "export=mesh"], None),
    (["log.eval_share=0.5", "log.eval_every=0"], "log.eval_share"),
    (["log.eval_share=0.5", "log.eval_every=5"], None),
]

#: keys a preset may set (Need.preset): refused only where the command line gives them
PRESET = {key for key, need in NEEDS.items() if need.preset}


def test_every_need_has_a_case():
    assert {key for _, key in CASES if key} == set(NEEDS)


@pytest.mark.parametrize(("overrides", "key"), CASES, ids=[" ".join(o) for o, _ in CASES])
def test_cli_check(overrides, key):
    config = OmegaConf.to_container(tiny_config(*overrides), resolve=True)
    if key is None:
        check_options(config, given_keys(overrides))
        return
    with pytest.raises(ConfigError, match=rf"^{key}: got .*, which does nothing without "):
        check_options(config, given_keys(overrides))


API = [(o, k) for o, k in CASES if not k or not (k.startswith("temporal") or k in PRESET)]


@pytest.mark.parametrize(("overrides", "key"), API, ids=[" ".join(o) for o, _ in API])
def test_python_api(overrides, key):
    """The same through fr.ReconstructionOptions (the run layer's scene and temporal aside, and
    the options a preset may set: the API keeps them for a later call, e.g. fr.confidence)."""
    config = OmegaConf.to_container(tiny_config(*overrides), resolve=True)
    make = lambda: fr.ReconstructionOptions.from_dict(config, ignore=RUN_LAYER_KEYS)
    if key is None:
        make().check()
        return
    with pytest.raises(ArgumentError, match=rf"^{key}: got "):
        make()


def test_what_a_preset_sets_for_a_switch_that_is_off_is_not_refused():
    """ScalarFlow's preset sets uncertainty.scale, the camera fit's calibration.* and the ladder
    for when they run: turned off on the command line (calibration.refine=none), or at a
    downscale where no rung runs, they are kept without a word; given on the command line they
    are refused."""
    for overrides in (["calibration.refine=none"], ["scene.downscale=4"], []):
        config = OmegaConf.to_container(compose_train(["scene=scalarflow", *overrides]), resolve=False)
        check_options(config, given_keys(overrides))
    given = ["calibration.refine=none", "calibration.frames=[30,70]"]
    with pytest.raises(ConfigError, match=r"^calibration\.frames: got \[30, 70\] .*, which does nothing without "
                                          r"a camera fit .*; set that too or drop calibration\.frames from the "
                                          r"command line$"):
        check_options(OmegaConf.to_container(compose_train(["scene=scalarflow", *given]), resolve=False),
                      given_keys(given))
    with pytest.raises(ConfigError, match=r"^uncertainty\.scale: got 5, which does nothing without the "
                                          r"confidence"):
        check_options(OmegaConf.to_container(compose_train(["scene=scalarflow", "uncertainty.scale=5"]),
                                             resolve=False), {"uncertainty.scale"})
