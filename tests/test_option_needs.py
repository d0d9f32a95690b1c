"""An option that does nothing in the combination given is refused by name, on the command
line (ConfigError, exit 2) and in the Python API (ArgumentError), from one table (NEEDS)."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.fit.option_rules import NEEDS, check_options
from flamerecon.run.folder import RUN_LAYER_KEYS
from tests.helpers import tiny_config

#: (overrides, the key refused; None: accepted): each NEEDS entry alone, then with what it needs
CASES = [
    (["select.auto=true", "select.candidates.fista=[]"], "select.auto"),
    (["select.auto=true", "solver=cgls"], "select.auto"),
    (["select.auto=true"], None),  # fista has candidates
    (["calibration.frames=[3,5]"], None),  # a preset's frames with calibration.refine=none: no refinement
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
]


def test_every_need_has_a_case():
    assert {key for _, key in CASES if key} == set(NEEDS)


@pytest.mark.parametrize(("overrides", "key"), CASES, ids=[" ".join(o) for o, _ in CASES])
def test_cli_check(overrides, key):
    config = OmegaConf.to_container(tiny_config(*overrides), resolve=True)
    if key is None:
        check_options(config)
        return
    with pytest.raises(ConfigError, match=rf"^{key}: got .*, which does nothing without "):
        check_options(config)


@pytest.mark.parametrize(("overrides", "key"), [c for c in CASES if not c[1] or not c[1].startswith("temporal")],
                         ids=[" ".join(o) for o, k in CASES if not k or not k.startswith("temporal")])
def test_python_api(overrides, key):
    """The same through fr.ReconstructionOptions (the run layer's scene and temporal aside)."""
    config = OmegaConf.to_container(tiny_config(*overrides), resolve=True)
    make = lambda: fr.ReconstructionOptions.from_dict(config, ignore=RUN_LAYER_KEYS)
    if key is None:
        make().check()
        return
    with pytest.raises(ArgumentError, match=rf"^{key}: got "):
        make()
