"""The run layer's :class:`~flamerecon.fit.reconstruct.SolveHook`: every solve of a CLI run
under the watchdog (:class:`~flamerecon.run.guard.SolveGuard`) with a TensorBoard monitor,
checkpoints in the run folder, resume from them and a stop on divergence."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

from flamerecon import interrupt
from flamerecon.errors import Interrupted, ResumeError, SolveDiverged
from flamerecon.evaluate.scores import render_scene_views, view_psnr
from flamerecon.fit.build import Setup
from flamerecon.fit.reconstruct import ResumePoint, SolveHook, Stage
from flamerecon.outputs.figures import heldout_figure, top_view
from flamerecon.run.checkpoint import CHECKPOINT_FILE
from flamerecon.run.guard import SolveGuard, StopSolve
from flamerecon.run.summary import cells_of
from flamerecon.run.tensorboard import RunWriter
from flamerecon.solvers import Problem, Solver, SolveResult

log = logging.getLogger(__name__)

#: ``watch(stage, iteration, x (M, C), info)``: called at every solver check (see :class:`RunHook`).
Watch = Callable[[Stage, int, torch.Tensor, dict], None]


class Monitor:
    """Solver callback: progress bar, TensorBoard scalars, held-out PSNR and pictures. Tags
    start with ``tag_root`` (``""`` for the final grid, ``level<i>/`` for coarse level i).

    The held-out views are rendered at most every ``eval_every`` iterations (0: never) and
    only while the monitor's own wall time, this render included (predicted from the last
    one), stays within ``eval_share`` of the solve's (None: no limit), so that past the first
    render (always made) they cost at most that share; on the final grid (``tag_root`` ``""``) never at the
    last iteration (``total``; 0 where the solver's count is not known ahead, as LARS's), whose
    pictures the run's final evaluation logs. :attr:`seconds` is the wall time spent here.
    """

    def __init__(self, setup: Setup, writer: RunWriter, eval_every: int, eval_share: float | None,
                 total: int, tag_root: str = ""):
        self.setup, self.writer = setup, writer
        self.every, self.share = int(eval_every), None if eval_share is None else float(eval_share)
        desc = "solve" if not tag_root else f"solve {tag_root.rstrip('/')}"
        self.bar = tqdm(total=int(total) or None, desc=desc, unit="it", leave=False, dynamic_ncols=True)
        self.tag_root = tag_root
        # the final grid's last iteration: its pictures come from the run's final evaluation
        self.left_to_evaluation = int(total) if not tag_root and int(total) > 0 else None
        self.last = 0
        self.started = time.perf_counter()
        self.seconds = 0.0
        self.render_seconds = 0.0  # the last render's cost: the next one's prediction
        self.last_pictures = 0

    def __call__(self, it: int, x: torch.Tensor, info: dict) -> None:
        now = time.perf_counter()
        self.bar.update(it - self.last)
        self.last = it
        self.bar.set_postfix(objective=f"{info['objective']:.4g}", gap=f"{info.get('rel_gap', math.nan):.1e}")
        values = {k: info[k] for k in ("objective", "data", "l1", "smooth", "tv", "rel_gap") if k in info}
        values["nonzero_fraction"] = float((x > 0).any(1).float().mean())
        self.writer.scalars(it, values, prefix=f"{self.tag_root}solve")
        affordable = self.share is None or self.last_pictures == 0 or (
            self.seconds + self.render_seconds <= self.share * (now - self.started))
        if self.every > 0 and it - self.last_pictures >= self.every and it != self.left_to_evaluation and affordable:
            start = time.perf_counter()
            self.pictures(it, x)
            self.render_seconds = time.perf_counter() - start
            self.last_pictures = it
        self.seconds += time.perf_counter() - now

    def pictures(self, it: int, x: torch.Tensor) -> None:
        """Render the held-out views of the iterate x (M, C) and log them."""
        s = self.setup
        vol = s.volume(x.detach())
        self.log_pictures(it, vol, render_scene_views(vol, s.grid, s.scene, s.holdout, s.step))

    def log_pictures(self, it: int, vol: torch.Tensor, imgs: torch.Tensor) -> None:
        log_pictures(self.writer, self.setup, it, vol, imgs, self.tag_root)

    def close(self) -> None:
        self.bar.close()


def log_pictures(writer: RunWriter, setup: Setup, it: int, vol: torch.Tensor, imgs: torch.Tensor,
                 root: str = "") -> None:
    """Held-out PSNR, held-out renders imgs (V, C, H, W) beside the captured views, and the top
    view of vol (C, nz, ny, nx), at step ``it``, under the tag prefix ``root``."""
    s = setup
    values = [view_psnr(img, s.scene, v) for img, v in zip(imgs, s.holdout)]
    if values:  # none with every camera fitted
        writer.scalars(it, {"heldout_psnr": sum(values) / len(values)}, prefix=f"{root}eval")
    for img, v in zip(imgs, s.holdout):
        writer.image(f"{root}heldout/{s.scene.views[v]}", heldout_figure(*shrunk(img, s.scene.images[v]),
                                                                        s.scene.views[v]), it, "HWC")
    writer.image(f"{root}density/top_view", top_view(vol, s.grid.bbox_min, s.grid.bbox_max, s.scene.up), it, "HWC")


def announce(text: str | None) -> None:
    """Print ``text`` (a run's composed config) when there is one: what a hook's
    :meth:`~flamerecon.fit.reconstruct.SolveHook.begin` does once the run's checks have passed."""
    if text:
        print(text, flush=True)


#: image rows a TensorBoard picture of a view keeps at most: larger views are averaged down by an
#: integer factor (a full-resolution ScalarFlow figure was 3 x 1080 x 1920 pixels, encoded at every check)
PICTURE_ROWS = 540


def shrunk(*images: torch.Tensor) -> list[torch.Tensor]:
    """Images (C, H, W) averaged over factor x factor blocks, the smallest integer factor that
    brings H to at most :data:`PICTURE_ROWS` (1: as they are)."""
    factor = -(-int(images[0].shape[-2]) // PICTURE_ROWS)
    if factor <= 1:
        return list(images)
    return [F.avg_pool2d(image.detach().float().cpu()[None], factor, ceil_mode=True)[0] for image in images]


@dataclass(frozen=True)
class RunOptions:
    """The run layer's ``log:`` and ``checkpoint:`` nodes."""

    eval_every: int = 20
    eval_share: float | None = 0.1
    checkpoint_every: int = 100
    divergence_factor: float = 1.0e3


class RunHook(SolveHook):
    """Each solve under the run's watchdog in ``run_dir``: a :class:`Monitor` (tags under
    ``level<i>/`` for coarse level i), checkpoints holding the problem's identity and the
    core's ``carry``, a stop on divergence, :class:`~flamerecon.errors.Interrupted` after a
    checkpoint on SIGINT/SIGTERM. With ``checkpoint`` (a loaded ``checkpoint.pt``) the solve
    of the stage it was written in continues from it.

    ``watch(stage, iteration, x, info)``, when given, is called after the monitor at every
    check of every solve (tests send a SIGINT from it at a chosen stage and iteration).
    ``announce``, when given, is printed once the checks before any work have passed.

    A coarse level that diverges raises :class:`~flamerecon.errors.SolveDiverged` (nothing is
    written); on the final grid the last good iterate comes back with ``stopped`` set.
    :attr:`monitor_seconds` is the monitors' time on the final grid, :attr:`stop` the
    divergence stop.
    """

    def __init__(self, run_dir: str | Path, writer: RunWriter, options: RunOptions,
                 plan: list[list[int]], checkpoint: dict | None = None, watch: Watch | None = None,
                 announce: str | None = None):
        self.run_dir, self.writer, self.options = Path(run_dir), writer, options
        self.plan, self.checkpoint, self.watch, self.announce = plan, checkpoint, watch, announce
        self.monitor_seconds = 0.0
        self.stop: StopSolve | None = None
        self.point = None if checkpoint is None else resume_point(self.run_dir, checkpoint["meta"], plan)

    def resume(self) -> ResumePoint | None:
        """The stage the checkpoint was written in, until that stage's solve has resumed."""
        return self.point

    def begin(self) -> None:
        announce(self.announce)

    def solve(self, stage: Stage, setup: Setup, problem: Problem, solver: Solver,
              x0: torch.Tensor | None, carry: dict) -> SolveResult:
        meta = {"solver": solver.name, "shape": list(setup.operator.shape),
                "channels": int(setup.pixels.shape[1]), "l1": problem.l1, "level": stage.level,
                "levels": self.plan, "round": stage.round}
        point = self.point
        here = self.checkpoint if point is not None and (point.level, point.round) == (stage.level, stage.round) else None
        if here is None and x0 is not None and stage.round == 0:  # where the warm start begins
            self.writer.scalars(0, {"objective": problem.objective(x0)}, prefix=f"{stage.tag_root}solve")
        result, stopped, monitor = self.guarded(stage, setup, problem, solver, meta, carry, x0, here)
        if here is not None:
            self.checkpoint = self.point = None  # resumed: the later stages start afresh
        if stage.final:
            self.monitor_seconds += monitor.seconds
        if stopped is not None:
            if not stage.final:
                raise SolveDiverged(
                    f"{self.run_dir}: the solve on {stage} ({cells_of(setup.grid.resolution)} cells) "
                    f"{stopped}; nothing was written; try a smaller step (solver.lr), another solver, "
                    "or other grid.levels"
                )
            self.stop = stopped
            result.stopped = str(stopped)
        return result

    def guarded(self, stage: Stage, setup: Setup, problem: Problem, solver: Solver, meta: dict,
                carry: dict, x0: torch.Tensor | None, ckpt: dict | None
                ) -> tuple[SolveResult, StopSolve | None, Monitor]:
        """The solve under :class:`~flamerecon.run.guard.SolveGuard`; (result, divergence stop or
        None, monitor)."""
        start, seconds_before = 0, 0.0
        if ckpt is not None:
            x0, start, seconds_before = resume_solver(self.run_dir, ckpt, solver, meta)
        start_x = x0 if x0 is not None else setup.pixels.new_zeros(problem.A.shape[1], problem.b.shape[1])
        start_objective = float(problem.objective(setup.pixels.new_zeros(start_x.shape)))
        o = self.options
        monitor = Monitor(setup, self.writer, o.eval_every, o.eval_share, int(getattr(solver, "max_iters", None) or 0),
                          stage.tag_root)
        monitor.last = monitor.last_pictures = start
        observe = monitor
        if self.watch is not None:
            def observe(it: int, x: torch.Tensor, info: dict) -> None:
                monitor(it, x, info)
                self.watch(stage, it, x, info)
        guard = SolveGuard(solver, observe, self.run_dir, o.checkpoint_every, o.divergence_factor,
                           start_objective, {**meta, **carry}, (start, start_x), seconds_before)
        stopped: StopSolve | None = None
        try:
            with interrupt.deferred():
                try:
                    try:
                        result = solver.solve(problem, x0=x0, callback=guard)
                    except interrupt.Stopped as stop:  # raised between chunks, away from a check
                        if stop.forced:  # a second signal: at once, no checkpoint
                            raise
                        guard.stop_here(*guard.last_good, stop.signal)
                    if interrupt.received():  # after the last check
                        guard.stop_here(result.iterations, result.x, interrupt.received())
                    result.seconds = guard.seconds()
                except StopSolve as stop:
                    if stop.reason == "interrupted":
                        where = "" if stage.final else f" of {stage} ({cells_of(setup.grid.resolution)} cells)"
                        where += f" (photometry refit {stage.round})" if stage.round else ""
                        raise Interrupted(
                            f"{self.run_dir}: {stop.detail} at iteration {stop.iteration}{where}; the state is "
                            f"saved in {CHECKPOINT_FILE}; continue with: python train.py resume={self.run_dir}"
                        ) from None
                    stopped = stop
                    it, x = guard.last_good
                    log.error("solve %s; keeping the last good iterate (iteration %d)", stop, it)
                    result = SolveResult(x, it, guard.seconds(), problem.objective(x), False)
        finally:
            monitor.close()
        return result, stopped, monitor


def resume_point(run_dir: Path, meta: dict, plan: list[list[int]]) -> ResumePoint:
    """Where the checkpoint with ``meta`` continues: its stage and the core's carry. Refuses a
    checkpoint written under other ``grid.levels`` than ``plan``."""
    if meta.get("levels", plan) != plan:
        raise ResumeError(
            f"{run_dir / CHECKPOINT_FILE}: field 'levels' is {meta['levels']} but the run's config "
            f"now gives grid.levels as {plan}; resume with the grid.levels it was started with"
        )
    carry = {"level_records": list(meta.get("level_records", []))}
    if "photometry" in meta:
        carry["photometry"] = meta["photometry"]
    # a checkpoint without "level" predates grid.levels: it is the final grid's
    return ResumePoint(int(meta.get("level", len(plan))), int(meta.get("round", 0)), carry)


def resume_solver(run_dir: Path, ckpt: dict, solver, meta: dict) -> tuple[torch.Tensor, int, float]:
    """Load checkpoint ``ckpt`` of ``run_dir`` into ``solver``; returns (x0, iteration, seconds
    so far). Refuses a checkpoint made for another problem (solver, operator shape, channels, l1)."""
    saved = ckpt["meta"]
    for key, now in meta.items():
        if key in saved and saved[key] != now:
            raise ResumeError(
                f"{run_dir / CHECKPOINT_FILE}: field '{key}' is {saved[key]} but the run's config now "
                f"gives {now}; the scene, grid or solver changed since the checkpoint"
            )
    state = ckpt["state"]
    if ckpt.get("exact"):
        solver.load_state(state)
    else:
        log.warning("%s: solver %s cannot restore its internal state; resuming from the saved "
                    "iterate (a warm start, not bit-identical to an uninterrupted run)",
                    run_dir / CHECKPOINT_FILE, meta["solver"])
    log.info("resuming %s from iteration %d", run_dir, state["iteration"])
    return state["x"], int(state["iteration"]), float(saved.get("seconds", 0.0))
