"""A full disk at any write of any tool loses nothing: every file already there stays byte for
byte (or is replaced by a complete new one written before the failure), nothing half-written
takes a final name, and the one-line error names the file that was being written."""

from __future__ import annotations

import errno
import json
import os
import runpy
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from flamerecon.outputs import atomic
from flamerecon.outputs.atomic import stale_temporaries, update_json_atomic
from flamerecon.run.pipeline import reconstruct
from tests.helpers import FAST, REPO, TINY, repo_env, tiny_config, tmpfs

#: appended streams that are not replaced whole (TensorBoard's event files, the run's log)
EXEMPT = ("events.out.tfevents", "train.log")


def script(name: str):
    return runpy.run_path(str(REPO / "scripts" / f"{name}.py"))["main"]


#: (tool, call on a finished run folder returning its exit status): every tool that writes
#: into a run folder, each with every kind of file it writes
TOOLS = {
    "render --figures": lambda run: script("render")(
        [str(run), "--figures", "--width", "32", "--height", "24"]),
    "render --turntable --camera": lambda run: script("render")(
        [str(run), "--turntable", "3", "--camera", "orbit:30,10", "--width", "32", "--height", "24"]),
    "export (every format)": lambda run: script("export")([str(run)]),
    "evaluate": lambda run: script("evaluate")([str(run), "--device", "cpu", "--no-native"]),
    "the run (pipeline)": lambda run: reconstruct(tiny_config(*FAST, "export.formats=[vti,ply]"), run) and 0,
}


class DiskFull:
    """atomic.py's commit, counted; the ``fail_at``-th one fails like a full disk (its
    temporary cut to half first, as a short write leaves it)."""

    def __init__(self, monkeypatch, fail_at: int | None = None) -> None:
        self.fail_at, self.written = fail_at, []
        commit = atomic._commit

        def failing(tmp, dest):
            self.written.append(dest)
            if len(self.written) == self.fail_at:
                os.truncate(tmp, tmp.stat().st_size // 2)
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            commit(tmp, dest)

        monkeypatch.setattr(atomic, "_commit", failing)


def snapshot(folder) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*")
            if p.is_file() and not p.name.startswith(EXEMPT)}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A tiny finished run on which every tool has run once (so that each finds its own good
    files from before)."""
    run = tmp_path_factory.mktemp("disk-full") / "run"
    result = subprocess.run([sys.executable, "train.py", *TINY, *FAST, f"hydra.run.dir={run}"],
                            cwd=REPO, env=repo_env(), capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr
    for tool in TOOLS.values():
        assert tool(run) == 0
    return run


@pytest.mark.parametrize("tool", TOOLS)
def test_disk_full_at_every_write_loses_nothing(tool, finished_run, tmp_path, monkeypatch, capsys):
    run = TOOLS[tool]
    count = DiskFull(monkeypatch)
    copy = shutil.copytree(finished_run, tmp_path / "count")
    assert run(copy) == 0
    writes = len(count.written)
    assert writes, f"{tool} wrote nothing through the atomic writer"
    for k in range(1, writes + 1):
        folder = shutil.copytree(finished_run, tmp_path / f"fail{k}")
        before = snapshot(folder)
        disk = DiskFull(monkeypatch, fail_at=k)
        capsys.readouterr()
        try:
            status = run(folder)
        except OSError as err:  # the Python API raises what a script prints
            status, message = 2, str(err)
        else:
            message = capsys.readouterr().err
        failed = disk.written[k - 1]
        assert status == 2, f"{tool}, disk full at write {k} ({failed}): exit {status}"
        assert f"{failed}: cannot write (errno 28 ENOSPC" in message, message
        after = snapshot(folder)
        changed = {p for p in after if before.get(p) != after[p]}
        assert changed <= set(disk.written[:k - 1]), f"{tool}: written outside the atomic writer: {changed}"
        if failed not in disk.written[:k - 1]:  # else a complete copy from earlier in this call
            assert after.get(failed) == before.get(failed), f"{tool}: {failed} changed by the failed write"
        assert not [t for d in {p.parent for p in after} for t in stale_temporaries(d, 0.0)]


def test_evaluate_keeps_the_fields_it_does_not_own(tmp_path):
    """A tool that updates metrics.json replaces its own fields and keeps the others."""
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps({"heldout": {"a": 1}, "timing": {"total": 3.0}, "note": "kept"}))
    merged = update_json_atomic(path, {"heldout": {"b": 2}, "solver": {"name": "x"}})
    assert json.loads(path.read_text()) == merged == {
        "heldout": {"b": 2}, "timing": {"total": 3.0}, "note": "kept", "solver": {"name": "x"}}


def test_evaluate_on_a_finished_run_keeps_timing(finished_run, tmp_path):
    run = shutil.copytree(finished_run, tmp_path / "run")
    timing = json.loads((run / "metrics.json").read_text())["timing"]
    assert script("evaluate")([str(run), "--device", "cpu", "--no-native"]) == 0
    assert json.loads((run / "metrics.json").read_text())["timing"] == timing


def test_hydra_config_save_is_atomic(tmp_path, monkeypatch, capsys):
    """train.py's ``.hydra/config.yaml``: a failed save keeps the old one and ends in the line."""
    from omegaconf import OmegaConf

    from flamerecon.run.train import save_config

    (tmp_path / "config.yaml").write_text("old: 1\n")
    DiskFull(monkeypatch, fail_at=1)
    with pytest.raises(SystemExit) as stop:
        save_config(OmegaConf.create({"new": 2}), "config.yaml", tmp_path)
    assert stop.value.code == 2
    assert f"{tmp_path / 'config.yaml'}: cannot write (errno 28" in capsys.readouterr().err
    assert (tmp_path / "config.yaml").read_text() == "old: 1\n"


@pytest.mark.slow
@pytest.mark.parametrize("free_kib", [2, 4, 8, 40, 100])
def test_render_on_a_real_full_tmpfs(finished_run, tmp_path, free_kib):
    """The case reported: render.py --figures on a nearly full disk (root only: mounts a tmpfs)."""
    with tmpfs(tmp_path / "disk", "size=2m") as disk:
        run = shutil.copytree(finished_run, disk / "run",
                              ignore=shutil.ignore_patterns("events.out.tfevents*", "*.vti", "*.ply"))
        before = snapshot(run)
        st = os.statvfs(disk)
        (disk / "fill").write_bytes(b"\0" * (st.f_bavail * st.f_frsize - free_kib * 1024))
        result = subprocess.run([sys.executable, "scripts/render.py", str(run), "--figures"], cwd=REPO,
                                env=repo_env(), capture_output=True, text=True, timeout=120, check=False)
        after = snapshot(run)
        assert result.returncode == 2 and "ENOSPC" in result.stderr, result.stderr
        assert result.stderr.count("\n") == 1, result.stderr  # the one line, no library noise
        changed = [p for p in before if after[p] != before[p]]
        # a figure small enough for what was free may be written (its title names this copy's
        # folder), and then whole: every file is its old bytes or a complete new picture
        assert all(p.suffix == ".png" and cv2.imdecode(np.frombuffer(after[p], np.uint8), cv2.IMREAD_UNCHANGED)
                   is not None for p in changed), changed
