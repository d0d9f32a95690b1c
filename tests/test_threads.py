"""Torch's CPU threads: ``threads`` as given, or null matched to the free cores (usable cores
less the threads other processes are running now, at least 1), set at every reconstruction's start, so it holds however
the program imported torch; the scripts import flamerecon before torch, so its OpenMP setting
is read."""

from __future__ import annotations

import ast
import os

import pytest
import torch

from flamerecon import device
from tests.helpers import REPO, TINY_API_SETUP, python_stdout


@pytest.mark.parametrize("cores, load, threads", [
    (2, 0.0, 2), (2, 0.4, 2), (2, 0.6, 1), (2, 1.2, 1), (2, 2.15, 1), (2, 4.4, 1),  # 2 shared cores
    (16, 3.2, 13), (16, 0.0, 16), (1, 0.0, 1), (1, 3.0, 1),
])
def test_the_default_is_the_cores_others_leave_free_at_least_one(cores, load, threads):
    assert device.free_cores(cores, load) == threads


@pytest.fixture
def machine(monkeypatch):
    """A machine of 4 usable cores where other processes run 1 thread now (this one's read
    makes 2 runnable); the default read afresh."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setattr(device, "runnable_threads", lambda: 2)
    monkeypatch.setattr(device.time, "sleep", lambda s: None)
    device.default_threads.cache_clear()
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)
    device.default_threads.cache_clear()


def test_null_threads_take_the_free_cores_and_a_number_is_kept(machine):
    assert device.set_threads(None) == 3 and torch.get_num_threads() == 3
    assert device.set_threads(1) == 1 and torch.get_num_threads() == 1


def test_the_default_is_read_once_per_process(machine, monkeypatch):
    assert device.default_threads() == 3
    monkeypatch.setattr(device, "runnable_threads", lambda: 5)  # this process's own solves
    assert device.default_threads() == 3


def test_busy_cores_is_the_median_of_its_reads_less_this_thread_and_ignores_the_load_average(monkeypatch):
    reads = iter([1, 3, 2, 9, 2])  # a short-lived process (9) does not count
    monkeypatch.setattr(device, "runnable_threads", lambda: next(reads))
    monkeypatch.setattr(device.time, "sleep", lambda s: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.3, 0.5, 0.2))  # a run that ended seconds ago
    assert device.busy_cores() == 1.0


def test_without_proc_loadavg_the_load_average_is_the_busy_cores(monkeypatch):
    monkeypatch.setattr(device, "runnable_threads", lambda: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (2.6, 0.5, 0.2))
    assert device.busy_cores() == 2.6


@pytest.mark.skipif(device.runnable_threads() is None, reason="no /proc/loadavg (not Linux)")
def test_a_spinning_process_is_counted_busy():
    import subprocess
    import sys
    import time

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        assert device.busy_cores() >= 1
    finally:
        spin.kill()
        spin.wait()


def test_the_thread_count_holds_when_torch_was_imported_first():
    code = ("import torch; import flamerecon as fr; from flamerecon.device import default_threads; "
            f"{TINY_API_SETUP}; o = o.replace(threads=1); "
            "steps = {'reconstruct': lambda o: fr.reconstruct(s, o), 'build': lambda o: fr.build(s, o), "
            "'fit': lambda o: fr.fit(setup, o)}; "
            "setup = fr.build(s, o)\n"
            "for name, step in steps.items():\n"
            "    torch.set_num_threads(3); step(o); print(name, torch.get_num_threads())\n"
            "torch.set_num_threads(3); fr.reconstruct(s, o.replace(threads=None)); "
            "print('null', torch.get_num_threads() == default_threads())")
    assert python_stdout(code).split() == ["reconstruct", "1", "build", "1", "fit", "1", "null", "True"]


def first_import(tree: ast.Module, roots: tuple[str, ...]) -> float:
    """Line of the first top-level import of a module under ``roots`` (inf: none)."""
    for node in tree.body:
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        if any(n.split(".")[0] in roots for n in names):
            return node.lineno
    return float("inf")


@pytest.mark.parametrize("path", sorted([*(REPO / "scripts").glob("*.py"), REPO / "train.py"]), ids=lambda p: p.name)
def test_every_program_imports_flamerecon_before_torch(path):
    tree = ast.parse(path.read_text())
    assert first_import(tree, ("flamerecon",)) < first_import(tree, ("torch", "kornia"))
