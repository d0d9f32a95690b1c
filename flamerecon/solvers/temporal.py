"""Time as a prior: consecutive frames solved jointly, neighbours pulled towards each other.

Frame t has its own operator A_t (N_t, M_t) on its own visual hull, data b_t (N_t, C) and
weights; the joint problem is

    min  sum_t [0.5||A_t x_t - b_t||^2 + l1_t sum(x_t) + mu_t TV(x_t)]
         + sum_t [0.5 w2 ||P_t(x_{t+1} - x_t)||^2 + w1 ||P_t(x_{t+1} - x_t)||_1],   x_t >= 0,

with TV the spatial isotropic total variation of :mod:`~flamerecon.solvers.primal_dual_tv`
and P_t the restriction to the voxels in *both* frames' hulls (:func:`coupling_pairs`). The
intersection, not the union: a voxel outside frame t's hull is zero in frame t because its
silhouettes say so (carved, not estimated), and coupling there would drag the neighbour's
density towards zero exactly where the smoke moved to; the prior should only trade noise
between estimates the data leave uncertain in both frames. Smoke rises, so the pairing may
follow a coarse motion: voxel v of frame t against voxel v + s_t of frame t+1, with s_t the
whole-cell shift that best carries one frame's density onto the next (:func:`estimate_shift`).

Solved by the Condat-Vu primal-dual iteration over the stacked frames: the data terms and the
squared coupling enter through their gradient, L1 + nonnegativity through a shifted clamp,
spatial TV (dual: balls of radius mu_t) and temporal L1 (dual: boxes of half-width w1) through
their duals. With w1 = w2 = 0 the frames decouple and each is the single-frame ``tv`` problem.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise

import torch
import torch.nn.functional as F

from flamerecon import interrupt
from flamerecon.operators import HullGradient
from flamerecon.solvers.base import LinearOperator, power_norm_sq
from flamerecon.solvers.primal_dual_tv import project_balls, total_variation


@dataclass
class FrameProblem:
    """One frame: operator ``A`` (N, M), data ``b`` (N, C), absolute weights ``l1`` and ``tv``
    (mu), and its hull: ``grid_shape`` (nz, ny, nx), ``voxel_index`` (M,) sorted flat indices."""

    A: LinearOperator
    b: torch.Tensor
    l1: float
    tv: float
    grid_shape: tuple[int, int, int]
    voxel_index: torch.Tensor


@dataclass
class JointOptions:
    """Absolute temporal weights ``l2`` (w2) and ``tv`` (w1) and the iteration budget.
    ``dual_step`` balances primal and dual steps as in the ``tv`` solver; the solve stops when
    the iterate's relative change over ``check_every`` iterations is below ``tol``."""

    l2: float = 0.0
    tv: float = 0.0
    max_iters: int = 300
    tol: float = 1e-5
    check_every: int = 10
    dual_step: float = 1.0
    max_seconds: float | None = None


@dataclass
class JointResult:
    """Densities ``xs`` (one (M_t, C) per frame) and how the solve went."""

    xs: list[torch.Tensor]
    iterations: int
    seconds: float
    objective: float
    converged: bool
    history: list[dict] = field(default_factory=list)


def coupling_pairs(voxel_indices: list[torch.Tensor], grid_shape: tuple[int, int, int] | None = None,
                   shifts: list[tuple[int, int, int]] | None = None
                   ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """For each neighbouring pair (t, t+1) the positions (ia, ib) in x_t and x_{t+1} of the
    voxels both hulls hold (``voxel_indices``: sorted flat indices per frame). With ``shifts``
    (one (dx, dy, dz) in cells per pair; needs ``grid_shape`` (nz, ny, nx)) voxel v of frame t
    is paired with voxel v + shift of frame t+1: the coupling follows that motion."""
    pairs = []
    for t, (a, b) in enumerate(pairwise(voxel_indices)):
        target, keep = a, torch.ones_like(a, dtype=torch.bool)
        if shifts is not None and any(shifts[t]):
            nz, ny, nx = grid_shape
            dx, dy, dz = shifts[t]
            k, j, i = a // (ny * nx), (a // nx) % ny, a % nx
            keep = ((i + dx >= 0) & (i + dx < nx) & (j + dy >= 0) & (j + dy < ny)
                    & (k + dz >= 0) & (k + dz < nz))
            target = a + (dz * ny + dy) * nx + dx  # a constant offset: stays sorted
        keep &= torch.isin(target, b)
        pairs.append((keep.nonzero().squeeze(1), torch.searchsorted(b, target[keep])))
    return pairs


def estimate_shift(a: torch.Tensor, b: torch.Tensor, max_shift: int) -> tuple[int, int, int]:
    """The whole-cell motion (dx, dy, dz), each within +-``max_shift``, that best carries
    volume ``a`` (nz, ny, nx) onto ``b``: the argmax of sum_v a(v) b(v + s), by FFT on
    volumes zero-padded so that no shift wraps around."""
    p = int(max_shift)
    a, b = (F.pad(v.double(), (p, p, p, p, p, p)) for v in (a, b))
    corr = torch.fft.irfftn(torch.fft.rfftn(a).conj() * torch.fft.rfftn(b), s=a.shape)
    offsets = torch.arange(-p, p + 1, device=corr.device)
    window = torch.stack(torch.meshgrid(offsets, offsets, offsets, indexing="ij")).reshape(3, -1)
    values = corr[window[0] % a.shape[0], window[1] % a.shape[1], window[2] % a.shape[2]]
    dz, dy, dx = window[:, int(values.argmax())].tolist()
    return int(dx), int(dy), int(dz)


class TemporalDifference:
    """d_t = x_{t+1}[ib] - x_t[ia] for each neighbouring pair, and its adjoint.
    ``norm_sq_bound`` = 4: D^T D is a path Laplacian per voxel (degree <= 2)."""

    norm_sq_bound = 4.0

    def __init__(self, pairs: list[tuple[torch.Tensor, torch.Tensor]], sizes: list[int]) -> None:
        self.pairs, self.sizes = pairs, sizes

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        return [xs[t + 1][ib] - xs[t][ia] for t, (ia, ib) in enumerate(self.pairs)]

    def adjoint(self, ds: list[torch.Tensor], like: torch.Tensor) -> list[torch.Tensor]:
        out = [like.new_zeros(m, like.shape[1]) for m in self.sizes]
        for t, ((ia, ib), d) in enumerate(zip(self.pairs, ds)):
            out[t].index_add_(0, ia, -d)
            out[t + 1].index_add_(0, ib, d)
        return out


def joint_objective(frames: list[FrameProblem], opts: JointOptions, xs: list[torch.Tensor],
                    grads: list[HullGradient] | None = None,
                    T: TemporalDifference | None = None) -> dict[str, float]:
    """The joint objective at ``xs`` and its parts (float64 sums)."""
    grads = grads or [HullGradient(f.grid_shape, f.voxel_index) for f in frames]
    T = T or TemporalDifference(coupling_pairs([f.voxel_index for f in frames]),
                                [int(f.voxel_index.numel()) for f in frames])
    data = sum(0.5 * float(((f.A.forward(x) - f.b).double() ** 2).sum()) for f, x in zip(frames, xs))
    l1 = sum(f.l1 * float(x.double().sum()) for f, x in zip(frames, xs))
    tv = sum(f.tv * float(total_variation(D.forward(x)).sum()) for f, D, x in zip(frames, grads, xs))
    diffs = T.forward(xs)
    t2 = 0.5 * opts.l2 * sum(float((d.double() ** 2).sum()) for d in diffs)
    t1 = opts.tv * sum(float(d.double().abs().sum()) for d in diffs)
    return {"objective": data + l1 + tv + t2 + t1, "data": data, "l1": l1, "tv": tv,
            "temporal_l2": t2, "temporal_tv": t1}


def solve_joint(frames: list[FrameProblem], opts: JointOptions,
                x0: list[torch.Tensor] | None = None, norms_sq: list[float] | None = None,
                callback: Callable[[int, list[torch.Tensor], dict], None] | None = None,
                shifts: list[tuple[int, int, int]] | None = None) -> JointResult:
    """Condat-Vu on the joint problem (module doc), from ``x0`` (or zeros) and zero duals:

        x_t <- max(0, x_t - tau (grad_t + D_t^T y_t + T_t^T z + l1_t))
        y_t <- P_{mu_t}(y_t + sigma D_t(2 x_t' - x_t)),   z <- clip_{w1}(z + sigma T(2 x' - x))

    with grad_t = A_t^T(A_t x_t - b_t) + w2 (T^T T x)_t. The smooth part's Lipschitz constant
    is at most L = max_t 1.01||A_t||^2 + 4 w2, ||[D; T]||^2 <= 12 + 4 = 16; sigma =
    dual_step L / 32 and tau = 1 / (1.01 (L/2 + 16 sigma)) satisfy the convergence condition
    1/tau - sigma ||K||^2 > L/2 (Condat 2013, Thm 3.1). ``norms_sq``: the ||A_t||^2 when
    known (else power iteration); ``shifts``: a motion per neighbouring pair
    (:func:`coupling_pairs`). All tensors stay on ``b``'s device.
    """
    started = time.perf_counter()
    if opts.l2 < 0 or opts.tv < 0:
        raise ValueError(f"temporal weights must be >= 0, got l2={opts.l2}, tv={opts.tv}")
    device, dtype = frames[0].b.device, frames[0].b.dtype
    C = frames[0].b.shape[1]
    sizes = [int(f.voxel_index.numel()) for f in frames]
    grads_op = [HullGradient(f.grid_shape, f.voxel_index.to(device)) for f in frames]
    T = TemporalDifference(coupling_pairs([f.voxel_index.to(device) for f in frames],
                                          frames[0].grid_shape, shifts), sizes)
    xs = ([torch.zeros(m, C, dtype=dtype, device=device) for m in sizes] if x0 is None
          else [x.to(device, dtype).clamp_min(0).clone() for x in x0])
    norms_sq = norms_sq or [power_norm_sq(f.A, m, device, dtype) for f, m in zip(frames, sizes)]
    L = 1.01 * max(norms_sq) + 4.0 * opts.l2
    K_sq = HullGradient.norm_sq_bound + TemporalDifference.norm_sq_bound
    sigma = opts.dual_step * L / (2.0 * K_sq)
    tau = 1.0 / (1.01 * (0.5 * L + sigma * K_sq))
    ys = [torch.zeros(3, m, C, dtype=dtype, device=device) for m in sizes]
    zs = [torch.zeros(ia.numel(), C, dtype=dtype, device=device) for ia, _ in T.pairs]

    def smooth_grad(xs: list[torch.Tensor]) -> list[torch.Tensor]:
        g = [f.A.adjoint(f.A.forward(x) - f.b) for f, x in zip(frames, xs)]
        if opts.l2 > 0:
            g = [gt + opts.l2 * lt for gt, lt in zip(g, T.adjoint(T.forward(xs), xs[0]))]
        return g

    history: list[dict] = []
    converged, it = False, 0
    previous = [x.clone() for x in xs]
    for it in range(1, opts.max_iters + 1):
        interrupt.check()
        g = smooth_grad(xs)
        tz = T.adjoint(zs, xs[0]) if opts.tv > 0 else [0.0] * len(xs)
        new = [(x - tau * (gt + D.adjoint(y) + tzt + f.l1)).clamp_min_(0)
               for x, gt, D, y, tzt, f in zip(xs, g, grads_op, ys, tz, frames)]
        extra = [2.0 * n - x for n, x in zip(new, xs)]
        ys = [project_balls(y + sigma * D.forward(e), f.tv) for y, D, e, f in zip(ys, grads_op, extra, frames)]
        if opts.tv > 0:
            zs = [(z + sigma * d).clamp_(-opts.tv, opts.tv) for z, d in zip(zs, T.forward(extra))]
        xs = new
        if it % opts.check_every == 0 or it == opts.max_iters:
            change = (sum(float((x - p).double().pow(2).sum()) for x, p in zip(xs, previous))
                      / max(sum(float(x.double().pow(2).sum()) for x in xs), 1e-300)) ** 0.5
            info = {**joint_objective(frames, opts, xs, grads_op, T), "rel_change": change}
            history.append({"iteration": it, **info})
            if callback is not None:
                callback(it, xs, info)
            if change < opts.tol:
                converged = True
                break
            if opts.max_seconds is not None and time.perf_counter() - started > opts.max_seconds:
                break
            previous = [x.clone() for x in xs]
    objective = joint_objective(frames, opts, xs, grads_op, T)["objective"]
    return JointResult(xs, it, time.perf_counter() - started, objective, converged, history)
