"""The typed reader every loader reads its files through (flamerecon/scenes/values.py): any
value a JSON, YAML or cv2.FileStorage file can hold comes back as the type asked for or as one
SceneError line naming the file and the field; a number written as a string is never parsed, a
fraction never truncated, one name never split into letters. The per-format tables of damaged
files are in tests/test_scenes_{opencv,nerf,pinf}.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flamerecon.run.config import options_from_config
from flamerecon.scenes import SceneError
from flamerecon.scenes.synthetic import load as load_synthetic
from flamerecon.scenes.values import (
    POSITIVE,
    read_float,
    read_int,
    read_matrix,
    read_names,
    read_size,
    read_text,
)
from tests.helpers import tiny_config

FILE, FIELD = "calib.json", "cameras[1].width"
#: what a parsed calibration file can hold where a value belongs
VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9), st.floats(), st.text(max_size=6),
              st.sampled_from(["40", "4e1", " 7 ", "nan", "-0.5", "..."])),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=3), inner, max_size=2)),
    max_leaves=8,
)
READERS = {
    "int": lambda v: read_int(v, FILE, FIELD),
    "float": lambda v: read_float(v, FILE, FIELD),
    "positive": lambda v: read_float(v, FILE, FIELD, POSITIVE),
    "text": lambda v: read_text(v, FILE, FIELD),
    "names": lambda v: read_names(v, FILE, FIELD),
    "vector": lambda v: read_matrix(v, (3,), FILE, FIELD),
    "size": lambda v: read_size(v, FILE, FIELD, "[H, W]"),
}


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


@pytest.mark.parametrize("reader", list(READERS))
@settings(max_examples=150, deadline=None)
@given(value=VALUES)
def test_a_value_is_read_as_asked_or_refused_naming_file_and_field(reader, value):
    try:
        got = READERS[reader](value)
    except SceneError as err:
        assert str(err).startswith(f"{FILE}: {FIELD}") and "\n" not in str(err)
        return
    if reader == "int":
        assert type(got) is int and got >= 1 and is_number(value) and got == value
    elif reader in ("float", "positive"):
        assert type(got) is float and math.isfinite(got) and is_number(value) and got == value
        assert got > 0 or reader == "float"
    elif reader == "text":
        assert type(got) is str and got and got == str(value) and not isinstance(value, (list, dict))
    elif reader == "names":
        assert all(type(n) is str for n in got)
        assert got == ([] if value is None else [str(value)] if not isinstance(value, list) else got)
        assert not isinstance(value, str) or got == [value]  # one name, never its letters
    else:
        assert not isinstance(value, str) and not (isinstance(value, list) and any(isinstance(v, str) for v in value))
        assert np.isfinite(np.asarray(got, dtype=float)).all()
        if reader == "size":
            assert all(type(n) is int and n >= 1 for n in got) and len(got) == 2


@pytest.mark.parametrize("value, message", [
    ("40", r"got the string '40'; write a number \(an integer >= 1\) without quotes"),
    (40.5, r"got 40\.5; it must be an integer >= 1"),
    (True, r"got True; it must be an integer >= 1"),
    (None, r"missing; it must be an integer >= 1"),
    ([40], r"got \[40\]; it must be an integer >= 1"),
    (float("nan"), r"got nan; it must be an integer >= 1"),
])
def test_an_image_size_is_never_coerced(value, message):
    with pytest.raises(SceneError, match=rf"^calib\.json: cameras\[1\]\.width: {message}$"):
        read_int(value, FILE, FIELD)


@pytest.mark.parametrize("key, value", [("width", "48"), ("width", 4.5), ("n_cameras", 1), ("noise", -0.1),
                                        ("peak", "0.8"), ("phantom_step", 0), ("frame", -1), ("seed", 0.5),
                                        ("field", "candle"), ("calibration_error", -1.0), ("azimuths", [0, 90])])
def test_the_synthetic_loader_reads_its_config_through_the_reader(key, value):
    with pytest.raises(SceneError, match=rf"^config: scene\.{key}: got "):
        load_synthetic({"name": "synthetic", key: value})


def test_one_holdout_name_on_the_command_line_is_one_view():
    assert options_from_config(tiny_config("holdout=cam03")).holdout == ("cam03",)
    assert options_from_config(tiny_config("holdout=[cam03,cam04]")).holdout == ("cam03", "cam04")
