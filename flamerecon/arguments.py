"""The front door's argument checks: every public function and class of :mod:`flamerecon`
checks what it is given with these before any work, and refuses it with
:class:`~flamerecon.errors.ArgumentTypeError` (the wrong type: None, a dict for options, an
int tensor for a density) or :class:`~flamerecon.errors.ArgumentError` (the wrong shape, out of
range, NaN), one line naming the argument, what it got and what it wants::

    render.volume: got a float32 tensor of shape (3, 8, 8); render.volume must be (C, nz, ny, nx)

Tensors of any floating dtype and on any device are taken (the callee converts them where it
needs to); numpy arrays are taken as tensors.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import functools
import numbers
import types
import typing
from pathlib import Path

import numpy as np
import torch

from flamerecon.errors import ArgumentError, ArgumentTypeError
from flamerecon.rules import Check, of_type


def describe(value) -> str:
    """A short description of ``value`` for a message: tensors and arrays by dtype and shape
    (and device), others by their repr (cut at 60 characters) and type."""
    if isinstance(value, torch.Tensor):
        dtype = str(value.dtype).removeprefix("torch.")
        return f"a {dtype} tensor of shape {tuple(value.shape)} on {value.device}"
    if isinstance(value, np.ndarray):
        return f"a {value.dtype} array of shape {value.shape}"
    if value is None or isinstance(value, (bool, numbers.Number)):
        return repr(value)
    text = repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return text if isinstance(value, str) else f"{text} ({type(value).__name__})"


def wrong_type(name: str, value, want: str) -> ArgumentTypeError:
    return ArgumentTypeError(f"{name}: got {describe(value)}; {name} must be {want}")


def wrong_value(name: str, value, want: str) -> ArgumentError:
    return ArgumentError(f"{name}: got {describe(value)}; {name} must be {want}")


def value(name: str, given, check: Check, null: bool = False):
    """``given`` when ``check`` passes (or it is None and ``null``), else the error for it."""
    if given is None and null:
        return given
    want = check(given)
    if want is None:
        return given
    want += " or None" if null else ""
    raise (wrong_value if of_type(given, check) else wrong_type)(name, given, want)


def instance(name: str, given, kinds: type | tuple[type, ...], want: str = "", null: bool = False):
    """``given`` when it is an instance of ``kinds`` (or None and ``null``), else
    :class:`ArgumentTypeError`; ``want`` words the kinds (default: their names)."""
    if (given is None and null) or isinstance(given, kinds):
        return given
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    want = want or " or ".join(f"a {k.__name__}" for k in kinds)
    raise wrong_type(name, given, want + (" or None" if null else ""))


def tensor(name: str, given, dims: str, ndim: int | None = None, shape: tuple | None = None,
           kind: str = "floating", finite: bool = False, null: bool = False) -> torch.Tensor | None:
    """``given`` as a tensor (a numpy array becomes one) of ``ndim`` dimensions and ``shape``
    (None entries: any size), named ``dims`` in messages (``"(C, nz, ny, nx)"``); ``kind``:
    ``floating`` (any float dtype), ``integer``, ``bool`` or ``any``; ``finite``: no NaN/Inf."""
    if given is None and null:
        return None
    if isinstance(given, np.ndarray):
        given = torch.from_numpy(given)
    if not isinstance(given, torch.Tensor):
        raise wrong_type(name, given, f"a tensor {dims}" + (" or None" if null else ""))
    if given.is_meta:
        raise ArgumentError(f"{name}: got a tensor on the 'meta' device, which holds no values; give {name} with "
                            "its values (on cpu or cuda)")
    kinds = {"floating": given.is_floating_point(), "any": True, "bool": given.dtype == torch.bool,
             "integer": not given.is_floating_point() and not given.is_complex() and given.dtype != torch.bool}
    if not kinds[kind]:
        raise wrong_type(name, given, f"a {kind} tensor {dims}")
    ndim = len(shape) if ndim is None and shape is not None else ndim
    if (ndim is not None and given.ndim != ndim) or (shape is not None and any(
            want is not None and int(want) != have for want, have in zip(shape, given.shape))):
        sizes = "" if shape is None else f" of shape ({', '.join('any' if s is None else str(int(s)) for s in shape)})"
        raise wrong_value(name, given, dims + sizes)
    if finite and given.numel() and not bool(torch.isfinite(given).all()):
        raise ArgumentError(f"{name}: holds NaN or Inf ({describe(given)}); {name} must be finite")
    return given


def one_or_many(given):
    """A list of names (or indices) as a list: one name (a string, an int) is a list of one,
    not of its characters; a tuple (any sequence) becomes a list; anything else is returned as it is (for the
    check that refuses it)."""
    if isinstance(given, (str, numbers.Integral)) and not isinstance(given, bool):
        return [given]
    return list(given) if isinstance(given, collections.abc.Sequence) else given


def fields(obj) -> None:
    """Refuse the first field of the dataclass instance ``obj`` whose value does not have the
    type its annotation says (``Setup.scene: got None; Setup.scene must be a Scene``)."""
    owner = type(obj).__name__
    for name, hint in _hints(type(obj)).items():
        given = getattr(obj, name)
        if not conforms(given, hint):
            raise wrong_type(f"{owner}.{name}", given, wording(hint))


@functools.cache
def _hints(cls: type) -> dict[str, object]:
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in typing.get_type_hints(cls).items() if k in names}


def conforms(given, hint) -> bool:
    """Whether ``given`` has the type ``hint`` (a class, a union, a generic alias such as
    ``list[int]`` or ``tuple[float, float, float]``, a Protocol by its members)."""
    if hint in (typing.Any, object):
        return True
    if hint is type(None):
        return given is None
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(conforms(given, h) for h in typing.get_args(hint))
    if origin is not None:
        if origin is collections.abc.Callable:
            return callable(given)
        if not isinstance(given, origin):
            return False
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        if origin in (list, tuple) and len(args) == 1:
            return all(conforms(v, args[0]) for v in given)
        if origin is tuple and args:
            return len(given) == len(args) and all(conforms(v, a) for v, a in zip(given, args))
        return True
    if hint is float:
        return isinstance(given, numbers.Real) and not isinstance(given, bool)
    if hint is int:
        return isinstance(given, numbers.Integral) and not isinstance(given, bool)
    if hint is Path:
        return isinstance(given, Path)
    if getattr(hint, "_is_protocol", False):
        members = [m for m in (*hint.__dict__, *getattr(hint, "__annotations__", {})) if not m.startswith("_")]
        return all(hasattr(given, m) for m in members)
    return isinstance(given, hint)


def wording(hint) -> str:
    """``hint`` in words: ``a Scene``, ``a Tensor or None``, ``a list of int``."""
    if hint is type(None):
        return "None"
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(wording(h) for h in typing.get_args(hint))
    if origin is not None:
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        inner = f" of {' and '.join(getattr(a, '__name__', str(a)) for a in args)}" if args else ""
        return f"a {origin.__name__}{inner}"
    return f"a {getattr(hint, '__name__', str(hint))}"
