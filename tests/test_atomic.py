"""Files are written whole or not at all: a killed or failing writer leaves the old file intact."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from flamerecon.outputs.atomic import (
    atomic_path,
    atomic_write_bytes,
    save_npz_atomic,
    stale_temporaries,
    write_json_atomic,
)
from tests.helpers import repo_env

REPO = Path(__file__).resolve().parents[1]

# The child writes a large first array into the archive, then announces it and blocks while
# numpy asks the second array for its data: it is killed in the middle of save_npz_atomic.
_CHILD = textwrap.dedent(
    """
    import signal, sys, time
    import numpy as np

    # a process started in the background by a shell inherits SIGINT ignored (and Python keeps
    # it so): this child is a user's process interrupted at the keyboard
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from flamerecon.outputs.atomic import save_npz_atomic

    class BlocksWhenRead:
        def __array__(self, dtype=None, copy=None):
            print("mid-write", flush=True)
            time.sleep(600)
            return np.zeros(1)

    big = np.full((4, 64, 128, 128), 7.0, dtype=np.float32)  # 16 MiB
    save_npz_atomic(sys.argv[1], density=big, views=BlocksWhenRead())
    """
)


def _start_child(dest: Path) -> subprocess.Popen:
    env = repo_env()
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(dest)], stdout=subprocess.PIPE, text=True, env=env
    )
    line = proc.stdout.readline()
    assert line.strip() == "mid-write", f"child did not reach the middle of the write: {line!r}"
    return proc


def _old_archive(dest: Path) -> np.ndarray:
    old = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    save_npz_atomic(dest, density=old)
    return old


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_killed_writer_leaves_old_file_intact(tmp_path, sig):
    dest = tmp_path / "density.npz"
    old = _old_archive(dest)
    proc = _start_child(dest)
    try:
        temps = [p for p in tmp_path.iterdir() if p != dest]
        assert len(temps) == 1 and temps[0].stat().st_size > 16 * 2**20, "write was not under way"
        proc.send_signal(sig)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
    assert proc.returncode != 0
    with np.load(dest) as f:
        assert sorted(f.files) == ["density"]
        np.testing.assert_array_equal(f["density"], old)
    left = [p for p in tmp_path.iterdir() if p != dest]
    if sig == signal.SIGINT:  # Python unwinds: the temporary is removed
        assert left == []
    else:  # no unwinding after SIGKILL: only the hidden temporary remains, recognisably named
        assert len(left) == 1 and left[0].name.startswith(".density.npz.")
        assert stale_temporaries(tmp_path, min_age_s=0) == left
        assert stale_temporaries(tmp_path, min_age_s=3600) == []


def test_exception_inside_atomic_path_removes_temporary(tmp_path):
    dest = tmp_path / "a.bin"
    atomic_write_bytes(dest, b"old")
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer failed")
    assert dest.read_bytes() == b"old"
    assert list(tmp_path.iterdir()) == [dest]


def test_written_file_has_usual_permissions(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    path = atomic_write_bytes(tmp_path / "a.bin", b"x")
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_temporary_keeps_suffix_and_folder(tmp_path):
    dest = tmp_path / "vol.vti"
    with atomic_path(dest) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".vti" and tmp != dest
        tmp.write_text("x")
    assert dest.read_text() == "x"


def test_writer_that_writes_nothing_is_an_error(tmp_path):
    dest = tmp_path / "x.txt"
    with pytest.raises(FileNotFoundError, match="x.txt"), atomic_path(dest) as tmp:
        tmp.unlink()
    assert not dest.exists()


def test_missing_folder_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        atomic_write_bytes(tmp_path / "nope" / "a.bin", b"")


def test_npz_and_json_round_trip(tmp_path):
    save_npz_atomic(tmp_path / "a.npz", x=np.ones(3), compressed=True)
    with np.load(tmp_path / "a.npz") as f:
        np.testing.assert_array_equal(f["x"], np.ones(3))
    with pytest.raises(ValueError, match="npz"):
        save_npz_atomic(tmp_path / "a.bin", x=np.ones(3))
    write_json_atomic(tmp_path / "m.json", {"psnr": np.float32(31.5), "v": np.arange(2)})
    assert json.loads((tmp_path / "m.json").read_text()) == {"psnr": 31.5, "v": [0, 1]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "m.json"]
