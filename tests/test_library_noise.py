"""A damaged PNG, MP4 or checkpoint ends train.py with its one error line: nothing that libpng,
ffmpeg or torch print or advise (``libpng error``, ``moov atom not found``, ``weights_only``)
reaches stderr."""

from __future__ import annotations

import collections
import pathlib
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from tests.helpers import REPO, repo_env, tiny_cfg

REAL = REPO.parent / "shared" / "data" / "scalarflow_real"
CAMERAS = [f"train0{i}" for i in range(5)]
SMALL = ["scene.downscale=8", "grid.resolution=16", "solver.max_iters=3", "device=cpu"]


def capture(folder: Path) -> Path:
    """The real capture linked file by file into ``folder`` (so one file can be damaged)."""
    if not REAL.is_dir():
        pytest.skip(f"no ScalarFlow capture at {REAL}")
    folder.mkdir()
    (folder / "info.json").write_bytes((REAL / "info.json").read_bytes())
    for camera in CAMERAS:
        (folder / camera).mkdir()
        for frame in (REAL / camera).glob("00000[0-1].png"):
            (folder / camera / frame.name).symlink_to(frame)
    return folder


def damaged_png(tmp_path: Path) -> list[str]:
    root = capture(tmp_path / "capture")
    png = root / "train01" / "000000.png"
    data = bytearray(png.read_bytes())
    data[2000:2100] = bytes(b ^ 0xFF for b in data[2000:2100])  # a filter byte libpng refuses
    png.unlink()
    png.write_bytes(bytes(data))
    return ["scene=scalarflow", f"scene.root={root}", "scene.frame=0", *SMALL]


def damaged_mp4(tmp_path: Path) -> list[str]:
    root = capture(tmp_path / "capture")
    for frame in (root / "train02").iterdir():
        frame.unlink()
    (root / "train02").rmdir()
    (root / "train02.mp4").write_bytes(b"\0\0\0\x18ftypmp42" + bytes(range(256)) * 8)  # no moov atom
    return ["scene=scalarflow", f"scene.root={root}", "scene.frame=1", *SMALL]


def foreign_checkpoint(tmp_path: Path) -> list[str]:
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(tiny_cfg(), run / ".hydra" / "config.yaml")
    torch.save({"state": collections.OrderedDict(path=pathlib.Path("x")), "meta": {}}, run / "checkpoint.pt")
    return [f"resume={run}"]


CASES = {  # case: (argv maker, the error line after "flamerecon: error: ")
    "damaged PNG": (damaged_png, r".*train01/000000\.png: cannot decode the image"),
    "MP4 without its moov atom": (damaged_mp4, r".*train02\.mp4: cannot open the video"),
    "checkpoint of Python objects": (foreign_checkpoint, (r".*checkpoint\.pt: unreadable checkpoint \(UnpicklingError: "
                                                         r"it holds a pathlib\.PosixPath, not only tensors")),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_damaged_file_ends_in_the_error_line_alone(case, tmp_path):
    make, message = CASES[case]
    argv = [*make(tmp_path), f"hydra.run.dir={tmp_path / 'out'}"]
    done = subprocess.run([sys.executable, "train.py", *argv], cwd=REPO, env=repo_env(), capture_output=True, check=False,
                          text=True, timeout=300)
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert [line for line in lines if not line.startswith("flamerecon: ")] == [], done.stderr  # nothing else
    errors = [line for line in lines if line.startswith("flamerecon: error: ")]
    assert len(errors) == 1 and re.fullmatch(f"flamerecon: error: {message}.*", errors[0]), errors
    assert "weights_only" not in done.stderr
