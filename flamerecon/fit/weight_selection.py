"""Regularisation weights chosen per capture, at run time, from its training views alone.

Leave-one-view-out on the operator already built: each fold drops the rows of one training
camera, solves every candidate weight setting on the remaining rows (warm-started along the
candidates in the order given, so a path from strong to weak weights costs a few solves, not a
grid of runs), debiases as the final solve will, and scores the dropped camera's full frame:
its rows predict what its rays see, every pixel outside them is predicted black (exact with
``projector.rays=hull``, whose rows cover every pixel the density can reach). The winner has
the highest mean PSNR over the folds.

Approximation, for speed: a fold keeps the visual hull carved by every training silhouette,
the dropped camera's too, so fold scores are a little optimistic for every candidate alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from flamerecon import interrupt
from flamerecon.fit.debias import DebiasOptions, debias
from flamerecon.operators.sparse import CsrOperator
from flamerecon.solvers import LinearOperator, Problem, make_solver, resolve_l1


@dataclass(frozen=True)
class SelectionOptions:
    """``candidates``: solver option overrides to compare (e.g. ``{"l1_rel": 0.05, "tv": 0.03}``),
    in path order (strongest first: each warm-starts the next); empty: no selection.
    ``folds``: at most this many training cameras are left out in turn (evenly spread).
    ``iterations``: the solver budget of each fold solve (None: the solver's own)."""

    candidates: tuple[dict, ...] = ()
    folds: int = 4
    iterations: int | None = None

    def __post_init__(self) -> None:
        if int(self.folds) < 2:
            raise ValueError(f"select.folds: must be at least 2, got {self.folds}")
        if self.iterations is not None and int(self.iterations) < 1:
            raise ValueError(f"select.iterations: must be at least 1 or null, got {self.iterations}")


class RowSubset:
    """The rows ``rows`` (R,) long of an operator (N, M): (R, M), for any backend."""

    def __init__(self, A: LinearOperator, rows: torch.Tensor):
        self.A, self.rows = A, rows
        self.shape = (int(rows.numel()), int(A.shape[1]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.A.forward(x)[self.rows]

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        full = y.new_zeros(self.A.shape[0], y.shape[1])
        full[self.rows] = y
        return self.A.adjoint(full)


def row_subset(A: LinearOperator, rows: torch.Tensor) -> LinearOperator:
    """The rows ``rows`` (R,) ascending of ``A``: sliced out of an assembled operator (a
    product then reads only those rows), else a :class:`RowSubset` view."""
    return A.rows(rows) if isinstance(A, CsrOperator) else RowSubset(A, rows)


def fold_views(num_train: int, folds: int) -> list[int]:
    """Positions (in the training list) of the cameras left out in turn: all of them, or
    ``folds`` evenly spread ones."""
    if num_train <= folds:
        return list(range(num_train))
    return sorted({round(i * (num_train - 1) / (folds - 1)) for i in range(folds)})


@dataclass
class Selection:
    """What the selection found: the winning overrides and every candidate's fold scores."""

    chosen: dict
    table: list[dict] = field(default_factory=list)  # per candidate: overrides, psnr, folds

    def record(self) -> dict:
        return {"chosen": self.chosen, "candidates": self.table}


def select_weights(solver: str, options: dict, selection: SelectionOptions, debias_options: DebiasOptions,
                   A: LinearOperator, b: torch.Tensor, row_view: torch.Tensor, view_energy: torch.Tensor,
                   view_pixels: int, names: list[str], geometry: dict | None = None) -> Selection:
    """Choose among ``selection.candidates`` for ``solver`` with base ``options`` (its config:
    ``l1``/``l1_rel`` and the solver's own keys) on the training rows ``A`` (N, M), ``b`` (N, C),
    ``row_view`` (N,) the training camera of each row, ``view_energy`` (T, C) the sum of squares
    of each training image over all its pixels, ``view_pixels`` = H * W; ``names``: training
    views' names for the table; ``geometry``: the :class:`Problem`'s ``grid_shape`` and
    ``voxel_index`` (smoothness-aware solvers need them)."""
    T = int(view_energy.shape[0])
    held = fold_views(T, int(selection.folds))
    scores: list[list[float]] = [[] for _ in selection.candidates]
    for k in held:
        keep = (row_view != k).nonzero().squeeze(1)
        out = (row_view == k).nonzero().squeeze(1)
        A_fit, b_fit = row_subset(A, keep), b[keep]
        A_out, b_out = row_subset(A, out), b[out]
        outside = float((view_energy[k].double().sum() - (b_out.double() ** 2).sum()).clamp_min(0))
        x = None
        for c, overrides in enumerate(selection.candidates):
            interrupt.check()
            x = solve_candidate(solver, {**options, **overrides}, selection.iterations, A_fit, b_fit,
                                x, geometry)
            xd, _ = debias(debias_options, A_fit, b_fit, x)
            err = float(((A_out.forward(xd).double() - b_out.double()) ** 2).sum()) + outside
            mse = err / (view_pixels * b.shape[1])
            scores[c].append(10.0 * math.log10(1.0 / mse) if mse > 0 else math.inf)
    table = [{"overrides": dict(o), "psnr": sum(s) / len(s),
              "folds": {names[k]: s[i] for i, k in enumerate(held)}}
             for o, s in zip(selection.candidates, scores)]
    best = max(range(len(table)), key=lambda i: table[i]["psnr"])
    return Selection(dict(selection.candidates[best]), table)


def solve_candidate(solver: str, options: dict, iterations: int | None, A: LinearOperator,
                    b: torch.Tensor, x0: torch.Tensor | None, geometry: dict | None = None
                    ) -> torch.Tensor:
    """One fold solve of ``solver`` with ``options`` (incl. ``l1``/``l1_rel``) from ``x0``."""
    opts = dict(options)
    l1, l1_rel = opts.pop("l1", None), opts.pop("l1_rel", None)
    if l1 is not None:
        l1_rel = None
    if iterations is not None:
        opts["max_iters"] = int(iterations)
    weight = resolve_l1(A, b, l1, l1_rel)
    problem = Problem(A, b, weight, **(geometry or {}))
    return make_solver(solver, **opts).solve(problem, x0=x0).x
