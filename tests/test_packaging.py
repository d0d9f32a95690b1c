"""``pip install .`` ships a working package: every package folder and the configs are in the
wheel, and its ``flamerecon`` command reconstructs the tiny flame from outside the checkout;
relative data paths resolve without Hydra and without machine-specific folders."""

from __future__ import annotations

import inspect
import json
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from flamerecon.resources import checkout_root, config_dir
from flamerecon.run.runner import anchor_scene_root
from flamerecon.scenes import SceneError, calibration
from flamerecon.scenes.calibration import resolve_root
from tests.helpers import FAST, REPO, TINY

tomllib = pytest.importorskip("tomllib")


def test_the_package_list_names_every_package_folder_and_the_configs():
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "flamerecon").rglob("__init__.py")}
    assert listed == folders | {"flamerecon.conf"}


def test_a_checkout_reads_its_top_level_configs():
    assert checkout_root() == REPO
    assert config_dir() == REPO / "conf" and (config_dir() / "train.yaml").is_file()


@pytest.mark.slow
@pytest.mark.e2e
def test_the_wheel_installs_and_its_command_runs_outside_the_checkout(tmp_path):
    source, wheels = tmp_path / "source", tmp_path / "wheels"  # a clean copy: no stale build/
    for name in ("flamerecon", "conf"):
        shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(wheels), str(source)], check=True, capture_output=True, cwd=tmp_path)
    (wheel,) = wheels.glob("flamerecon-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {n for n in names if n.startswith("flamerecon/conf/")}
    expected = {f"flamerecon/conf/{p.relative_to(REPO / 'conf').as_posix()}"
                for p in (REPO / "conf").rglob("*.yaml")}
    assert shipped == expected
    env_dir = tmp_path / "venv"
    bin_dir = borrowing_venv(env_dir)
    subprocess.run([sys.executable, "-m", "pip", "--python", str(bin_dir / "python"), "install", "-q",
                    "--no-deps", str(wheel)], check=True, capture_output=True, cwd=tmp_path)
    where = subprocess.run(
        [str(bin_dir / "python"), "-c", ("import flamerecon.resources as r; "
                                         "print(r.PACKAGE, r.config_dir(), r.checkout_root())")],
        check=True, capture_output=True, text=True, cwd=tmp_path).stdout.split()
    assert Path(where[0]).is_relative_to(env_dir) and where[1] == str(Path(where[0]) / "conf")
    assert where[2] == "None"
    run = tmp_path / "run"
    proc = subprocess.run([str(bin_dir / "flamerecon"), *TINY, *FAST, f"hydra.run.dir={run}"],
                          check=False, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["solver"]["iterations"] == 10 and (run / "density.npz").is_file()
    assert (run / "train.log").is_file()  # the job keeps the name it had as python train.py
    api = subprocess.run(  # the installed API reads the CLI's run folder back to its metrics
        [str(bin_dir / "python"), "-c", (f"import flamerecon as fr; r = fr.load_run({str(run)!r}, 'cpu'); "
                                         "print(fr.score(r)['heldout']['cam04']['psnr'])")],
        check=True, capture_output=True, text=True, cwd=tmp_path, timeout=300).stdout
    assert float(api) == pytest.approx(metrics["heldout"]["cam04"]["psnr"], rel=1e-6)


def borrowing_venv(env_dir: Path) -> Path:
    """A fresh venv at ``env_dir`` that imports its dependencies from the folders the running
    interpreter imports from (its ``sys.path``, listed in a ``.pth`` file, after the venv's own
    site-packages), the checkout left out; returns its bin folder. ``system_site_packages``
    would give the base interpreter's packages instead, which inside a venv lack them."""
    venv.create(env_dir, with_pip=False)
    bin_dir = env_dir / ("Scripts" if sys.platform == "win32" else "bin")
    site = subprocess.run([str(bin_dir / "python"), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          check=True, capture_output=True, text=True).stdout.strip()
    borrowed = [p for p in sys.path if p and Path(p).is_dir() and Path(p).resolve() != REPO]
    (Path(site) / "borrowed-from-the-test-interpreter.pth").write_text("\n".join(borrowed) + "\n")
    return bin_dir


def test_a_relative_scene_root_resolves_against_where_the_command_started(tmp_path, monkeypatch):
    (tmp_path / "data").mkdir()
    cfg = OmegaConf.create({"scene": {"name": "x", "root": "data"}})
    anchor_scene_root(cfg, tmp_path)
    assert cfg.scene.root == str((tmp_path / "data").resolve())
    for root in ("elsewhere", "???", None):  # not under the start, missing, none: left as they are
        cfg = OmegaConf.create({"scene": {"name": "x", "root": root}})
        anchor_scene_root(cfg, tmp_path)
        assert OmegaConf.to_container(cfg)["scene"]["root"] == root
    monkeypatch.chdir(tmp_path)
    assert resolve_root("data") == (tmp_path / "data").resolve()  # then the working directory
    assert resolve_root("conf") == REPO / "conf"  # then the checkout
    with pytest.raises(SceneError, match=r"scene.root: 'nowhere' does not exist \(tried .*nowhere, .*nowhere\)"):
        resolve_root("nowhere")
    assert "hydra" not in inspect.getsource(calibration)
