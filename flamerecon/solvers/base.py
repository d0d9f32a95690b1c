"""The one interface every solver shares.

A solver minimises, per colour channel and over hull voxels,

    F(x) = 0.5 * ||A x - b||_2^2 + l1 * sum(x)      subject to x >= 0

(the paper's eq. 6 up to the factor 1/2; ``sum(x) == ||x||_1`` on the feasible set), where
``A`` is any :class:`LinearOperator` (the projector restricted to silhouette rays x hull
voxels), ``b`` (N, C) the pixel values and ``x`` (M, C) the voxel densities. The C columns
(R, G, B) share A and are solved together.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from flamerecon import interrupt
from flamerecon.arguments import conforms, tensor, value, wrong_type, wrong_value
from flamerecon.operators.base import LinearOperator, norm_sq
from flamerecon.rules import integer, list_of, number


@dataclass
class Problem:
    """A nonnegative LASSO: operator ``A``, data ``b`` (N, C), absolute weight ``l1`` >= 0.

    Optional hull geometry for smoothness-aware solvers: ``grid_shape`` (nz, ny, nx) and
    ``voxel_index`` (M,) long, the flat index (x fastest) of each unknown in that grid.
    """

    A: LinearOperator
    b: torch.Tensor
    l1: float = 0.0
    grid_shape: tuple[int, int, int] | None = None
    voxel_index: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if not conforms(self.A, LinearOperator):
            raise wrong_type("Problem.A", self.A, "a LinearOperator (shape (N, M), forward, adjoint)")
        N, M = (int(n) for n in self.A.shape)
        self.b = tensor("Problem.b", self.b, "(N, C) with N = A.shape[0]", shape=(N, None), finite=True)
        self.l1 = float(value("Problem.l1", self.l1, number(0)))
        value("Problem.grid_shape", self.grid_shape, list_of(integer(1), 3, "(nz, ny, nx) of integers >= 1"),
              null=True)
        self.voxel_index = index = tensor("Problem.voxel_index", self.voxel_index, "(M,) with M = A.shape[1]", shape=(M,),
                       kind="integer", null=True)
        if index is not None and self.grid_shape is not None and M and not (
                0 <= int(index.min()) and int(index.max()) < math.prod(self.grid_shape)):
            raise wrong_value("Problem.voxel_index", index, f"flat indices in [0, {math.prod(self.grid_shape)})")

    def objective_parts(self, x: torch.Tensor) -> dict[str, float]:
        """Data term 0.5||Ax-b||^2, L1 term l1*sum|x| and their sum, as Python floats."""
        r = self.A.forward(x) - self.b
        data = 0.5 * float((r.double() ** 2).sum())
        l1 = self.l1 * float(x.double().abs().sum())
        return {"objective": data + l1, "data": data, "l1": l1}

    def objective(self, x: torch.Tensor) -> float:
        return self.objective_parts(x)["objective"]


def duality_gap(
    problem: Problem, x: torch.Tensor, residual: torch.Tensor, grad: torch.Tensor
) -> tuple[float, float]:
    """Primal value and duality gap of the nonnegative LASSO at a feasible ``x``.

    ``residual`` = A x - b (N, C) and ``grad`` = A^T residual (M, C). The dual point is the
    negated residual scaled per channel into the feasible set {u : A^T u <= l1}.
    """
    r = residual.double()
    b = problem.b.double()
    primal = 0.5 * (r**2).sum(0) + problem.l1 * x.double().sum(0)
    worst = (-grad.double()).amax(0)  # max_j (A^T u)_j for u = -r
    if problem.l1 == 0:
        # nonnegative least squares: the dual point -r is feasible only once A^T r >= 0, and
        # scaling cannot make it so; use the KKT residual x.g + ||x||_1 max(0, -min g)
        # instead, which equals the duality gap whenever -r is feasible and vanishes at x*
        g = grad.double()
        kkt = (x.double() * g).sum(0).clamp_min(0) + x.double().sum(0) * worst.clamp_min(0)
        return float(primal.sum()), float(kkt.sum())
    scale = torch.where(worst > problem.l1, problem.l1 / worst.clamp_min(1e-300), torch.ones_like(worst))
    u = -r * scale
    dual = (b * u).sum(0) - 0.5 * (u**2).sum(0)
    return float(primal.sum()), float((primal - dual).clamp_min(0).sum())


def gap_report(problem: Problem, x: torch.Tensor, residual: torch.Tensor, grad: torch.Tensor) -> dict[str, float]:
    """A solver's report at a feasible ``x``: objective, its data and L1 terms, the duality gap
    and the gap relative to the objective (:func:`duality_gap`; ``residual`` = A x - b (N, C),
    ``grad`` = A^T residual (M, C))."""
    primal, gap = duality_gap(problem, x, residual, grad)
    return {
        "objective": primal,
        "data": 0.5 * float((residual.double() ** 2).sum()),
        "l1": problem.l1 * float(x.double().sum()),
        "gap": gap,
        "rel_gap": gap / max(primal, 1e-30),
    }


@dataclass
class SolveResult:
    """What a solve returns: densities (M, C) and how it got there."""

    x: torch.Tensor
    iterations: int
    seconds: float
    objective: float
    converged: bool
    history: list[dict] = field(default_factory=list)
    stopped: str | None = None  # why a guard stopped the solve early (x: its last good iterate)


Callback = Callable[[int, torch.Tensor, dict], None]


class Solver:
    """Base class: :meth:`solve` times :meth:`_run`, which by default is the iteration every
    iterative solver shares (CIL's ``Algorithm.run`` style): :meth:`set_up`, then :meth:`step`
    up to ``max_iters`` times; at every ``check_every``-th iteration and the last,
    :meth:`report` -> history, resume state, callback, then stop when :meth:`reached` says the
    tolerance is met, at ``max_iters`` or past ``max_seconds``. A subclass writes those hooks
    (its update step and its measures); a solver that is no such loop overrides :meth:`_run`.
    """

    name = "base"
    max_seconds: float | None = None

    def __init__(self, max_iters: int = 500, tol: float = 1e-4, check_every: int = 10,
                 max_seconds: float | None = None) -> None:
        """The budget iterative solvers share: at most ``max_iters`` iterations, stop below
        ``tol`` (each solver's own criterion), tested every ``check_every`` iterations, and at
        the first test past ``max_seconds`` of wall time (None: no limit)."""
        self.max_iters = int(max_iters)
        self.tol = float(tol)
        self.check_every = max(1, int(check_every))
        self.max_seconds = None if max_seconds is None else float(max_seconds)

    def out_of_time(self) -> bool:
        """Whether this :meth:`solve` has run past ``max_seconds``."""
        return self.max_seconds is not None and time.perf_counter() - self._started > self.max_seconds

    def solve(
        self, problem: Problem, x0: torch.Tensor | None = None, callback: Callback | None = None
    ) -> SolveResult:
        M = problem.A.shape[1]
        C = problem.b.shape[1]
        x = (
            torch.zeros(M, C, dtype=problem.b.dtype, device=problem.b.device)
            if x0 is None
            else x0.to(problem.b).clamp_min(0).clone()
        )
        self._started = time.perf_counter()
        result = self._run(problem, x, callback)
        result.seconds = time.perf_counter() - self._started
        return result

    def _run(self, problem: Problem, x: torch.Tensor, callback: Callback | None) -> SolveResult:
        resume = self._take_resume()
        self.history: list[dict] = [] if resume is None else list(resume["history"])
        start = self.set_up(problem, x, resume)
        converged, it = self.reached_at_start(), start - 1
        for it in range(start, self.max_iters + 1) if not converged else ():
            interrupt.check()  # a stop signal recorded during the solve, acted on within an iteration
            self.step(it)
            if not self.is_check(it):
                continue
            info = self.report(it)
            converged = self._checked(it, info, callback)
            if converged or it == self.max_iters or self.out_of_time():
                break
            self.after_check(info)
        x, objective = self.result(problem)
        return SolveResult(x, it, 0.0, objective, converged, self.history)

    def _checked(self, it: int, info: dict, callback: Callback | None) -> bool:
        """At a check: ``info`` into the history, the resume state set and the callback called
        (it may add entries to ``info``); whether the tolerance is met."""
        entry = {"iteration": it, **info}
        self.history.append(entry)
        if callback is not None:
            self._state = self.snapshot(it)
            callback(it, self.x, info)
            entry.update(info)
        return self.reached(info)

    # The hooks of the shared loop. ``self.x`` (M, C) is the current iterate throughout.
    def set_up(self, problem: Problem, x: torch.Tensor, resume: dict | None) -> int:
        """Prepare the iteration from ``x`` (M, C), or from ``resume`` (a :meth:`state`, whose
        ``x`` is ``x``); returns the number of the first iteration to run."""
        raise NotImplementedError

    def step(self, it: int) -> None:
        """Iteration ``it``: the solver's update of ``self.x``."""
        raise NotImplementedError

    def is_check(self, it: int) -> bool:
        """Whether iteration ``it`` reports, may stop and calls the callback."""
        return it % self.check_every == 0 or it == self.max_iters

    def report(self, it: int) -> dict[str, float]:
        """The measures at a check: at least ``objective``, ``data`` and ``l1``."""
        raise NotImplementedError

    def reached(self, info: dict) -> bool:
        """Whether the solver's stopping tolerance is met at the check that reported ``info``."""
        return info["rel_gap"] < self.tol

    def reached_at_start(self) -> bool:
        """Whether the starting point already meets the tolerance (then no iteration runs)."""
        return False

    def after_check(self, info: dict) -> None:
        """Bookkeeping after a check that did not stop (step-size control, ...)."""

    def snapshot(self, it: int) -> dict | None:
        """What :meth:`state` returns at the check of iteration ``it``; None: no exact resume."""
        return None

    def result(self, problem: Problem) -> tuple[torch.Tensor, float]:
        """The final densities (M, C) and their objective."""
        return self.x, problem.objective(self.x)

    # Optional exact resume (checkpoints): a solver that supports it returns from
    # :meth:`snapshot` the dict it needs to go on, and reads its ``resume`` in :meth:`set_up`.
    _state: dict | None = None
    _resume: dict | None = None

    def state(self) -> dict | None:
        """At a callback: what the solver needs to continue exactly from there (tensors, numbers,
        lists; ``torch.save``-able), or None where it only supports a warm start from ``x``."""
        return self._state

    def load_state(self, state: dict) -> None:
        """Make the next :meth:`solve` continue from ``state`` (from :meth:`state`), so that it
        ends where an uninterrupted solve would; pass the same problem and ``x0 = state['x']``."""
        self._resume = state

    def _take_resume(self) -> dict | None:
        state, self._resume = self._resume, None
        return state


SOLVERS: dict[str, type[Solver]] = {}


def register(name: str):
    """Class decorator adding a solver to :data:`SOLVERS` under ``name``."""

    def deco(cls: type[Solver]) -> type[Solver]:
        cls.name = name
        SOLVERS[name] = cls
        return cls

    return deco


def option_names(cls: type[Solver]) -> list[str]:
    """The keyword options a solver class takes: its ``__init__``'s, and those of the classes
    it passes ``**options`` on to."""
    names: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        params = list(inspect.signature(init).parameters.values())[1:]  # past self
        names |= {p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return sorted(names)


def make_solver(name: str, **options) -> Solver:
    """Instantiate the solver registered as ``name`` with its options; an option it does not
    take is a ValueError naming it and listing the valid ones."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver '{name}': choose one of {sorted(SOLVERS)}")
    valid = option_names(SOLVERS[name])
    unknown = [key for key in options if key not in valid]
    if unknown:
        raise ValueError(
            f"solver.{unknown[0]}: unknown option of solver '{name}'; valid: {', '.join(valid)} "
            "(and name, l1, l1_rel)"
        )
    return SOLVERS[name](**options)


def power_norm_sq(A: LinearOperator, M: int, device, dtype=torch.float32, iters: int = 30, seed: int = 0) -> float:
    """Estimate ||A||_2^2 (largest eigenvalue of A^T A) by power iteration, cached on ``A``
    (:func:`flamerecon.operators.norm_sq`; ``M`` is ``A.shape[1]``)."""
    if M != A.shape[1]:
        raise ValueError(f"power_norm_sq: M={M} but the operator has {A.shape[1]} columns")
    return norm_sq(A, device, dtype, iters, seed)


def density_scale(A: LinearOperator, b: torch.Tensor) -> torch.Tensor:
    """Per-channel best constant density c (C,) minimising ||A (c 1) - b||: <A1, b>/||A1||^2.

    A unit-free scale for step sizes; 1 where the fit is degenerate (A 1 = 0 or c <= 0).
    """
    ones = torch.ones(A.shape[1], 1, dtype=b.dtype, device=b.device)
    a1 = A.forward(ones).double()
    denom = float((a1 * a1).sum())
    c = (a1 * b.double()).sum(0) / max(denom, 1e-300)
    return torch.where(c > 0, c, torch.ones_like(c)).to(b.dtype)


def lambda_max(A: LinearOperator, b: torch.Tensor) -> float:
    """max_j (A^T b)_j over voxels and channels: the smallest l1 for which x = 0 is optimal."""
    return max(float(A.adjoint(b).max()), 0.0)


def resolve_l1(
    problem_or_A: Problem | LinearOperator,
    b: torch.Tensor | None = None,
    l1: float | None = 0.0,
    l1_rel: float | None = None,
) -> float:
    """The absolute L1 weight from the config: ``l1`` as given, or ``l1_rel * lambda_max``.

    ``problem_or_A`` is a :class:`Problem` (then ``b`` defaults to its data) or an operator
    with ``b`` (N, C). Setting both ``solver.l1`` and ``solver.l1_rel`` nonzero is an error.
    """
    if isinstance(problem_or_A, Problem):
        A, b = problem_or_A.A, problem_or_A.b if b is None else b
    else:
        A = problem_or_A
    l1 = 0.0 if l1 is None else float(l1)
    if l1 < 0:
        raise ValueError(f"solver.l1 must be >= 0, got {l1}")
    if l1_rel is None:
        return l1
    l1_rel = float(l1_rel)
    if l1_rel < 0:
        raise ValueError(f"solver.l1_rel must be >= 0, got {l1_rel}")
    if l1 != 0.0 and l1_rel != 0.0:
        raise ValueError(f"set either solver.l1 ({l1}) or solver.l1_rel ({l1_rel}), not both")
    if b is None:
        raise ValueError("resolve_l1: solver.l1_rel needs the data b to compute max(A^T b)")
    return l1_rel * lambda_max(A, b) if l1_rel != 0.0 else l1
