"""The monitor's held-out renders stay within their share of the solve (on a fake clock), and a
run reports where its time went (metrics.json ``timing``, the summary's time split)."""

from __future__ import annotations

import json

import pytest

from flamerecon.run import hook as run_hook
from flamerecon.run import pipeline
from tests.helpers import tiny_cfg


class Clock:
    """A fake ``time.perf_counter``: advances only when told."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Writer:
    def scalars(self, step, values, prefix="solve") -> None:
        pass


@pytest.mark.parametrize("share", [0.1, None])
def test_monitor_renders_within_its_share_of_the_solve(monkeypatch, share):
    clock = Clock()
    monkeypatch.setattr(run_hook.time, "perf_counter", clock)
    renders = []

    def pictures(self, it, x):  # a render costs 1 s, ten solver iterations
        renders.append(it)
        clock.t += 1.0

    monkeypatch.setattr(run_hook.Monitor, "pictures", pictures)
    monitor = run_hook.Monitor(None, Writer(), eval_every=1, eval_share=share, total=0)
    x = run_hook.torch.zeros(4, 3)
    start = clock.t
    for it in range(1, 1001):
        clock.t += 0.1  # one solver iteration
        monitor(it, x, {"objective": 1.0})
    monitor.close()
    elapsed = clock.t - start
    if share is None:
        assert len(renders) == 1000  # every log.eval_every iterations, as before
    else:
        assert 5 <= len(renders) <= 15 and renders[0] == 1
        assert monitor.seconds <= share * elapsed + 1e-9
        assert monitor.seconds == pytest.approx(len(renders) * 1.0)


def test_the_first_render_is_made_even_when_the_monitor_is_over_its_share(monkeypatch):
    """The default run's solve is short and its scalars already cost more than 10% of it: its
    first held-out render (iteration 20) is made all the same, so TensorBoard shows the solve."""
    clock = Clock()
    monkeypatch.setattr(run_hook.time, "perf_counter", clock)
    renders = []

    def pictures(self, it, x):
        renders.append(it)
        clock.t += 1.0

    monkeypatch.setattr(run_hook.Monitor, "pictures", pictures)
    monitor = run_hook.Monitor(None, Writer(), eval_every=20, eval_share=0.1, total=100)
    monitor.seconds = 5.0  # as if the monitor had spent everything already
    for it in range(1, 101):
        clock.t += 0.01
        monitor(it, run_hook.torch.zeros(4, 3), {"objective": 1.0})
    assert renders == [20]


def test_a_run_folder_is_named_by_its_scene_solver_and_frame():
    """TensorBoard names its runs by their folders: hydra.run.dir says what each run was."""
    import re

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from tests.helpers import REPO

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        for overrides, name in (([], "synthetic_pqn_smooth_f0"), (["solver=fista"], "synthetic_fista_f0"),
                                (["scene=scalarflow", "scene.frame=25"], "scalarflow_tv_f25")):
            cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
            folder = OmegaConf.to_container(cfg.hydra.run, resolve=True)["dir"]
            assert re.fullmatch(rf"outputs/\d{{4}}-\d\d-\d\d/\d\d-\d\d-\d\d_{name}", folder), folder


def test_the_last_iteration_is_not_rendered_twice(monkeypatch):
    renders = []
    monkeypatch.setattr(run_hook.Monitor, "pictures", lambda self, it, x: renders.append(it))
    monitor = run_hook.Monitor(None, Writer(), eval_every=10, eval_share=None, total=30)
    for it in range(1, 31):
        monitor(it, run_hook.torch.zeros(4, 3), {"objective": 1.0})
    monitor.close()
    assert renders == [10, 20]  # the run's final evaluation logs iteration 30's pictures


def test_a_run_reports_its_time_split(tmp_path):
    metrics = pipeline.reconstruct(tiny_cfg("log.eval_every=5"), tmp_path)
    timing = metrics["timing"]
    assert {"scene", "setup", "assembly", "solve", "monitoring", "outputs", "total"} <= set(timing)
    assert all(v >= 0 for v in timing.values())
    assert timing["assembly"] <= timing["setup"]
    assert timing["total"] == pytest.approx(sum(v for k, v in timing.items()
                                                if k not in ("assembly", "total")))
    assert json.loads((tmp_path / "metrics.json").read_text())["timing"] == timing
    assert "time split [s]" in pipeline.summary_table(metrics)
