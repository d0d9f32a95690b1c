"""Joint frame solves (scene.frames) against independent per-frame solves, on held-out views.

    PYTHONPATH=. python scripts/temporal_eval.py scene=scalarflow scene.frames=[30,34] \
        --weights 0:0 0.01:0 0:0.03:shift [--absorption] [more overrides ...]

Every frame is prepared once (silhouettes, hull, operator). Then, per frame, the baseline:
the single-frame solver of the config (``solver=tv``: the pipeline's own solve), and per
``--weights L2:TV[:shift]`` (temporal.l2, temporal.tv, temporal.motion) one joint solve of
all frames. Prints, per
frame and method, held-out PSNR (each held-out view), mean training PSNR and solve seconds
(the joint solve's seconds are for all frames together), then the means. With
``--absorption ITERS`` each method's densities are also refitted with emission + absorption
(:mod:`flamerecon.fit.absorption`) and scored through the absorbing renderer, beside the same
refit with sigma held at 0 with ``--control`` (what the refit alone does); only the first
method's.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import os
import sys
import time

import numpy as np

from flamerecon.device import set_threads
from flamerecon.errors import ConfigError
from flamerecon.evaluate.scores import score
from flamerecon.fit.joint_frames import (
    JointFramesOptions,
    joint_solve_options,
    prepare_frames,
    solve_frames,
)
from flamerecon.run.cli import at_least, compose_train, run_script, script_parser
from flamerecon.run.config import options_from_config
from flamerecon.run.joint_frames import frame_config, frame_range
from flamerecon.run.pipeline import resolve_device, solve
from flamerecon.scenes import load_scene


def weights(text: str) -> tuple[float, float, str]:
    """argparse type: 'L2:TV[:shift]' -> (l2, tv, temporal.motion), weights >= 0."""
    parts = text.split(":")
    try:
        l2, tv = float(parts[0]), float(parts[1])
    except (ValueError, IndexError):
        l2 = tv = -1.0
    if len(parts) > 3 or l2 < 0 or tv < 0 or parts[2:] not in ([], ["shift"]):
        raise argparse.ArgumentTypeError(f"got '{text}'; give L2:TV or L2:TV:shift, weights >= 0")
    return l2, tv, "shift" if len(parts) == 3 else "none"


def scores(setup, volume) -> tuple[dict[str, float], float]:
    """({held-out view: PSNR}, mean training PSNR) of a density on its frame."""
    metrics, _ = score(setup.scene, volume, setup.grid, setup.train, setup.holdout, setup.step)
    held = {k: v["psnr"] for k, v in metrics["heldout"].items()}
    return held, float(np.mean([v["psnr"] for v in metrics["train"].values()]))


def absorbing_scores(setup, problem, volume, iters: int, fit_sigma: bool = True
                     ) -> tuple[dict[str, float], float, float, float]:
    """Refit ``volume`` with absorption (``fit_sigma=False``: the same refit with sigma = 0, the
    control) under the frame's own l1 and tv weights (``problem``); (held-out PSNRs, training
    PSNR, sigma, seconds)."""
    from flamerecon.fit.absorption import AbsorptionOptions, fit_absorption, score_absorbing

    started = time.perf_counter()
    fit = fit_absorption(setup, volume, problem.l1, problem.tv,
                         AbsorptionOptions(iters=iters, fit_sigma=fit_sigma))
    seconds = time.perf_counter() - started
    held, train = score_absorbing(setup, fit.volume, fit.sigma)
    print(f"  absorption refit (fit_sigma={fit_sigma}): sigma {fit.sigma_start:.4g} -> {fit.sigma:.4g}, "
          f"loss {fit.losses[0]:.6g} -> {fit.losses[-1]:.6g}", flush=True)
    return held, train, fit.sigma, seconds


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="config overrides; must set scene.frames")
    parser.add_argument("--weights", nargs="+", type=weights, default=[weights("0:0")], metavar="L2:TV[:shift]",
                        help="temporal.l2 and temporal.tv of a joint solve, ':shift' for temporal.motion=shift")
    parser.add_argument("--no-baseline", action="store_true", help="skip the per-frame solves")
    parser.add_argument("--absorption", type=at_least(0), default=0, metavar="ITERS",
                        help="also refit the first method's result with absorption, ITERS Adam steps")
    parser.add_argument("--control", action="store_true",
                        help="with --absorption, also the same refit with sigma held at 0")
    args = parser.parse_args(argv)
    return run_script(lambda: run(args), args.debug)


def run(args: argparse.Namespace) -> None:
    cfg = compose_train(args.overrides, default_scene=None)
    if cfg.scene.get("frames") is None:
        raise ConfigError("scene.frames: not set; give the frames to solve jointly, e.g. scene.frames=[30,34]")
    set_threads(cfg.get("threads"))
    device = resolve_device(cfg.device)
    started = time.perf_counter()
    numbers = frame_range(cfg)
    configs = [frame_config(cfg, t) for t in numbers]
    options = options_from_config(cfg)
    prepared = prepare_frames([load_scene(c.scene) for c in configs], options, device)
    print(f"prepared {len(numbers)} frames in {time.perf_counter() - started:.1f} s; "
          f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    rows = []  # (method, frame, held-out {view: psnr}, train psnr, seconds)
    methods: list[tuple[str, list]] = []
    if not args.no_baseline:
        volumes, seconds = [], []
        for fcfg, setup in zip(configs, prepared.setups):
            result, _, _ = solve(fcfg, setup)
            volumes.append(setup.volume(result.x))
            seconds.append(result.seconds)
        methods.append((f"per-frame {cfg.solver.name}", list(zip(volumes, seconds))))
    for l2, tv, motion in args.weights:
        joint = JointFramesOptions(l2=l2, tv=tv, tol=float(cfg.temporal.tol))
        opts = joint_solve_options(options, joint, prepared)
        result, shifts = solve_frames(prepared, opts, motion, int(cfg.temporal.max_shift))
        volumes = [s.volume(x) for s, x in zip(prepared.setups, result.xs)]
        if shifts is not None:
            print(f"l2={l2:g} tv={tv:g}: shifts (dx, dy, dz) between frames {shifts}")
        label = f"joint l2={l2:g} tv={tv:g}" + (" shift" if shifts is not None else "")
        methods.append((f"{label} ({result.iterations} it)", [(v, result.seconds) for v in volumes]))
    for name, per_frame in methods:
        for t, setup, problem, (volume, secs) in zip(numbers, prepared.setups,
                                                     prepared.problems, per_frame):
            held, train = scores(setup, volume)
            rows.append((name, t, held, train, secs))
            if args.absorption and name == methods[0][0]:
                held_a, train_a, sigma, secs_a = absorbing_scores(setup, problem, volume, args.absorption)
                rows.append((f"{name} +absorption (sigma {sigma:.3g})", t, held_a, train_a, secs_a))
                if args.control:
                    held_c, train_c, _, secs_c = absorbing_scores(setup, problem, volume, args.absorption,
                                                                  fit_sigma=False)
                    rows.append((f"{name} +same refit, sigma=0", t, held_c, train_c, secs_c))
    views = sorted(rows[0][2])
    print(f"{'method':<52} {'frame':>5} " + " ".join(f"{v:>9}" for v in views) + f" {'train':>7} {'sec':>7}")
    for name, t, held, train, secs in rows:
        print(f"{name:<52} {t:>5} " + " ".join(f"{held[v]:9.2f}" for v in views)
              + f" {train:7.2f} {secs:7.1f}")
    print("means over frames:")
    for name in dict.fromkeys(r[0].split(" (sigma")[0] for r in rows):
        sel = [r for r in rows if r[0].split(" (sigma")[0] == name]
        held = " ".join(f"{np.mean([r[2][v] for r in sel]):9.2f}" for v in views)
        print(f"{name:<52} {'mean':>5} {held} {np.mean([r[3] for r in sel]):7.2f}")
    print(f"load {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    sys.exit(main())
