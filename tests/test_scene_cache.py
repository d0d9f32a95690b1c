"""The rendered-scene cache (flamerecon/scenes/cache.py): a hit gives back the very tensors,
a damaged entry is recomputed, the switch turns it off, and the key follows options and code."""

from __future__ import annotations

import os
import sys

import pytest
import torch

from flamerecon.scenes import cache, load_scene
from tests.conftest import SMALL_SCENE

CODE = [sys.modules["flamerecon.scenes.cache"]]


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.ENV_DIR, str(tmp_path / "cache"))
    monkeypatch.delenv(cache.ENV_SWITCH, raising=False)
    return tmp_path / "cache"


def counted():
    """A compute function and the list its calls append to."""
    calls = []

    def compute():
        calls.append(1)
        return {"a": torch.arange(6.0).reshape(2, 3), "b": torch.tensor([1, 2], dtype=torch.int32)}

    return compute, calls


def test_a_hit_returns_the_same_tensors_without_computing(folder):
    compute, calls = counted()
    first = cache.cached("toy", {"n": 1}, compute, CODE)
    again = cache.cached("toy", {"n": 1}, compute, CODE)
    assert len(calls) == 1 and len(list(folder.glob("toy-*.pt"))) == 1
    assert all(torch.equal(first[k], again[k]) and first[k].dtype == again[k].dtype for k in first)


def test_the_synthetic_scene_from_the_cache_equals_the_rendered_one(folder, monkeypatch):
    hit = load_scene(dict(SMALL_SCENE))
    assert len(list(folder.glob("synthetic-*.pt"))) == 1
    hit = load_scene(dict(SMALL_SCENE))
    monkeypatch.setenv(cache.ENV_SWITCH, "0")
    fresh = load_scene(dict(SMALL_SCENE))
    assert torch.equal(hit.images, fresh.images) and torch.equal(hit.truth, fresh.truth)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "tampered"])
def test_a_damaged_entry_is_recomputed_and_replaced(folder, damage):
    compute, calls = counted()
    good = cache.cached("toy", {"n": 1}, compute, CODE)
    (path,) = folder.glob("toy-*.pt")
    if damage == "garbage":
        path.write_bytes(b"not a torch file")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:100])
    else:  # loads fine, but its tensors are not the ones its digest describes
        entry = torch.load(path, weights_only=True)
        entry["tensors"]["a"][0, 0] = 99.0
        torch.save(entry, path)
    got = cache.cached("toy", {"n": 1}, compute, CODE)
    assert len(calls) == 2 and torch.equal(got["a"], good["a"])
    assert torch.equal(cache.cached("toy", {"n": 1}, compute, CODE)["a"], good["a"]) and len(calls) == 2


@pytest.mark.parametrize("switch", ["0", "off", "False", "no"])
def test_the_switch_turns_the_cache_off(folder, monkeypatch, switch):
    monkeypatch.setenv(cache.ENV_SWITCH, switch)
    compute, calls = counted()
    cache.cached("toy", {"n": 1}, compute, CODE)
    cache.cached("toy", {"n": 1}, compute, CODE)
    assert len(calls) == 2 and not folder.exists()


def test_the_key_follows_the_options_and_the_code(folder):
    key = cache.entry_key("toy", {"n": 1}, CODE)
    assert key == cache.entry_key("toy", {"n": 1}, CODE)
    assert key != cache.entry_key("toy", {"n": 2}, CODE)
    assert key != cache.entry_key("toy", {"n": 1}, CODE + [sys.modules["flamerecon.outputs.atomic"]])


def test_an_unwritable_cache_folder_only_costs_the_compute(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv(cache.ENV_DIR, str(blocker / "cache"))  # a folder under a file
    compute, calls = counted()
    cache.cached("toy", {"n": 1}, compute, CODE)
    cache.cached("toy", {"n": 1}, compute, CODE)
    assert len(calls) == 2


def test_old_entries_beyond_the_limit_go_first(folder, monkeypatch):
    monkeypatch.setattr(cache, "MAX_ENTRIES", 2)
    compute, _ = counted()
    for n in range(3):
        cache.cached("toy", {"n": n}, compute, CODE)
        path = folder / f"toy-{cache.entry_key('toy', {'n': n}, CODE)[:32]}.pt"
        os.utime(path, (1_000_000 + n, 1_000_000 + n))  # distinct ages, whatever the clock's grain
    names = {p.name for p in folder.glob("toy-*.pt")}
    assert len(names) == 2
    assert f"toy-{cache.entry_key('toy', {'n': 0}, CODE)[:32]}.pt" not in names


def test_large_entries_of_one_kind_never_evict_small_entries_of_another(folder, monkeypatch):
    """Each kind keeps its own budget: many large entries of one kind evict only their own
    oldest, by count and by bytes, and another kind's small entry stays."""
    monkeypatch.setattr(cache, "MAX_ENTRIES", 3)
    monkeypatch.setattr(cache, "MAX_BYTES", 250_000)  # two of the 100 kB entries below, not three
    small, _ = counted()
    cache.cached("small", {"n": 0}, small, CODE)
    for n in range(6):
        cache.cached("large", {"n": n}, lambda: {"x": torch.zeros(25_000)}, CODE)
        os.utime(folder / f"large-{cache.entry_key('large', {'n': n}, CODE)[:32]}.pt", (1e6 + n, 1e6 + n))
    assert len(list(folder.glob("small-*.pt"))) == 1
    kept = {p.name for p in folder.glob("large-*.pt")}
    assert kept == {f"large-{cache.entry_key('large', {'n': n}, CODE)[:32]}.pt" for n in (4, 5)}


def test_the_newest_entry_stays_even_beyond_the_byte_budget(folder, monkeypatch):
    monkeypatch.setattr(cache, "MAX_BYTES", 10)
    compute, calls = counted()
    cache.cached("toy", {"n": 1}, compute, CODE)
    cache.cached("toy", {"n": 1}, compute, CODE)
    assert len(calls) == 1
