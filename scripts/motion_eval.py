"""Motion-compensated windows (:mod:`flamerecon.dynamics.motion`) against the single-frame
reconstruction, on held-out views, per window length.

    PYTHONPATH=. python scripts/motion_eval.py --frames 62,67,72 --windows 1,3,5 \
        [--decay 0.5 1] [--smooth 0.01] [--control 8] [--fit-to density images] \
        [--pictures DIR] [scene=scalarflow by default, train.py overrides ...]

Per target frame t, every frame within the longest window of t is reconstructed on its own
(the config's single-frame reconstruction), the displacement from t to each neighbour is
fitted once per (smooth, control, fit_to), and frame t is solved again per window length and
decay with its neighbours' views carried onto it. Prints, per frame and setting, the held-out
PSNR, SSIM and detail correlation (mean over held-out views), the mean training PSNR and the
motion fit's relative residual (mean over neighbours: none = u 0 / whole-cell shift / fitted),
then the means over frames. Window 1 is the single-frame reconstruction. ``--pictures DIR``
writes, per frame, the held-out view captured beside each setting's render (PNG).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import sys
import time
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import numpy as np

from flamerecon.dynamics.motion import MotionOptions, estimate_window, prepare_window, solve_window
from flamerecon.errors import ConfigError
from flamerecon.run.cli import compose_train, frame_list, run_script, script_parser
from flamerecon.run.pipeline import options_from_config, resolve_device
from flamerecon.scenes import load_scene


def numbers(kind):
    def read(text: str) -> list:
        return [kind(v) for v in text.split(",") if v.strip()]
    return read


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py config overrides (scene=scalarflow by default)")
    parser.add_argument("--frames", type=frame_list, default=[62, 67, 72], help="target frames, e.g. 62,67,72")
    parser.add_argument("--windows", type=frame_list, default=[1, 3, 5], help="window lengths (odd), e.g. 1,3,5")
    parser.add_argument("--decay", type=float, nargs="+", default=[0.5], help="neighbour weights decay**|s-t|")
    parser.add_argument("--smooth", type=float, nargs="+", default=[0.01], help="motion smoothness weights")
    parser.add_argument("--control", type=int, default=8, help="motion control cells along the longest side")
    parser.add_argument("--fit-to", nargs="+", default=["density"], choices=["density", "images"],
                        help="fit the motion to the neighbours' densities or images")
    parser.add_argument("--static", action="store_true",
                        help="also each window with u = 0 (neighbours' views as if nothing moved)")
    parser.add_argument("--first", type=int, default=0, help="no neighbour before this frame")
    parser.add_argument("--last", type=int, default=None, help="no neighbour after this frame")
    parser.add_argument("--pictures", type=Path, default=None, help="write held-out comparisons here")
    args = parser.parse_args(argv)
    for w in args.windows:
        if w % 2 != 1:
            parser.error(f"argument --windows: got {w}; window lengths are odd (1, 3, 5, ...)")
    return run_script(lambda: run(args), args.debug)


def run(args) -> None:
    cfg = compose_train(args.overrides)
    options = options_from_config(cfg)
    if options.solver.name not in ("tv", "fista"):
        raise ConfigError(f"solver.name: motion compensation solves with tv or fista, got {options.solver.name}")
    device = resolve_device(cfg.device)
    half = max(args.windows) // 2
    rows = []  # (frame, label, window, heldout psnr, ssim, detail, train psnr, residuals)
    for t in args.frames:
        started = time.perf_counter()
        last = args.last if args.last is not None else t + half
        frames_here = [s for s in range(t - half, t + half + 1) if args.first <= s <= last]
        scenes = [load_scene({**cfg.scene, "frame": s}) for s in frames_here]
        frames = prepare_window(scenes, options, device)
        target = frames_here.index(t)
        print(f"frame {t}: {len(frames)} frames reconstructed on their own in "
              f"{time.perf_counter() - started:.0f} s", flush=True)
        pictures = []
        settings = [(f, s) for f in args.fit_to for s in args.smooth] + ([("static", 0.0)] if args.static else [])
        for fit_to, smooth in settings:
                motion = MotionOptions(window=max(args.windows), control=args.control, smooth=smooth,
                                       fit_to="density" if fit_to == "static" else fit_to)
                moves = (static_window(frames, target) if fit_to == "static"
                         else estimate_window(frames, target, motion))
                for s, d in sorted(moves.items()):
                    print(f"  {fit_to} smooth={smooth:g}: {t}->{frames_here[s]} shift {d.shift}, mean "
                          f"{d.record()['mean_cells']} cells, residual none {d.residual_none:.3f} / shift "
                          f"{d.residual_shift:.3f} / fitted {d.residual:.3f}; "
                          + neighbour_residuals(frames, target, s, d), flush=True)
                for window in args.windows:
                    for decay in (args.decay if window > 1 else [0.0]):
                        if window == 1 and (fit_to, smooth) != (args.fit_to[0], args.smooth[0]):
                            continue
                        w_opts = MotionOptions(window=window, decay=decay if window > 1 else 0.5,
                                               control=args.control, smooth=smooth, fit_to=motion.fit_to)
                        rec = solve_window(frames, target, options, w_opts, moves)
                        metrics = rec.score()
                        held = list(metrics["heldout"].values())
                        used = [d for s, d in moves.items() if abs(s - target) <= window // 2]
                        res = tuple(float(np.mean([getattr(d, k) for d in used])) if used else float("nan")
                                    for k in ("residual_none", "residual_shift", "residual"))
                        label = ("single frame" if window == 1 else f"static (u=0) decay={decay:g}"
                                 if fit_to == "static" else f"{fit_to} s={smooth:g} decay={decay:g}")
                        rows.append((t, label, window, np.mean([h["psnr"] for h in held]),
                                     np.mean([h["ssim"] for h in held]), np.mean([h["detail"] for h in held]),
                                     np.mean([v["psnr"] for v in metrics["train"].values()]), res))
                        print(f"  window {window} {label}: held-out {rows[-1][3]:.2f} dB, detail "
                              f"{rows[-1][5]:.3f} ({time.perf_counter() - started:.0f} s)", flush=True)
                        if args.pictures is not None:
                            pictures.append((f"w{window} {label}", rec))
        if args.pictures is not None and pictures:
            write_pictures(args.pictures, t, pictures)
    print(f"{'frame':>5} {'window':>6} {'setting':<34} {'PSNR':>7} {'SSIM':>7} {'detail':>7} {'train':>7} "
          f"{'motion residual none/shift/fit':>30}")
    for t, label, window, p, s, d, tr, res in rows:
        print(f"{t:>5} {window:>6} {label:<34} {p:7.2f} {s:7.4f} {d:7.3f} {tr:7.2f} "
              f"{res[0]:9.3f} {res[1]:9.3f} {res[2]:9.3f}")
    print("means over frames:")
    for key in dict.fromkeys((r[2], r[1]) for r in rows):
        sel = [r for r in rows if (r[2], r[1]) == key]
        print(f"{'mean':>5} {key[0]:>6} {key[1]:<34} {np.mean([r[3] for r in sel]):7.2f} "
              f"{np.mean([r[4] for r in sel]):7.4f} {np.mean([r[5] for r in sel]):7.3f} "
              f"{np.mean([r[6] for r in sel]):7.2f}  ({len(sel)} frames)")


def neighbour_residuals(frames, target: int, s: int, d) -> str:
    """How well frame ``target``'s own solution, carried by ``d``, explains frame ``s``'s pixels
    (||A_s W x_t - b_s||^2 / ||b_s||^2), beside u = 0 and frame s's own solution; and the part of
    the displacement that is not its mean translation (RMS over the target's hull, cells)."""
    import torch

    from flamerecon.operators.warp import warp_matrix

    here, there = frames[target].setup, frames[s].setup
    b = there.pixels.double()
    norm = float(b.pow(2).sum())

    def rel(y):
        return float((y.double() - b).pow(2).sum()) / norm

    x = frames[target].fit.result.x
    moved = rel(there.operator.forward(warp_matrix(d.u, here.voxel_index, there.voxel_index).forward(x)))
    still = rel(there.operator.forward(warp_matrix(torch.zeros_like(d.u), here.voxel_index,
                                                   there.voxel_index).forward(x)))
    own = rel(there.operator.forward(frames[s].fit.result.x))
    u = d.u.reshape(3, -1)[:, here.voxel_index.cpu()]
    spread = float((u - u.mean(1, keepdim=True)).pow(2).sum(0).mean().sqrt())
    return (f"neighbour pixels by x_t: u=0 {still:.4f}, moved {moved:.4f}, own x_s {own:.4f}; "
            f"non-translation {spread:.2f} cells")


def static_window(frames, target: int) -> dict:
    """u = 0 to every other frame (the neighbours' views as if nothing had moved)."""
    import torch

    from flamerecon.dynamics.motion import Displacement

    zero = torch.zeros(3, *frames[target].setup.grid.shape)
    return {s: Displacement(zero, zero[:, :2, :2, :2], (0, 0, 0), float("nan"), float("nan"), float("nan"))
            for s in range(len(frames)) if s != target}


def write_pictures(folder: Path, frame: int, entries: list) -> None:
    """``folder/frame_NNN_<view>.png``: the captured held-out view, then each entry's render."""
    import cv2
    import torch

    from flamerecon.geometry.cameras import camera_subset
    from flamerecon.operators.projector import render_image

    folder.mkdir(parents=True, exist_ok=True)
    rec0 = entries[0][1]
    for view in rec0.setup.holdout:
        panels = [rec0.scene.images[view]]
        for _, rec in entries:
            cams = camera_subset(rec.scene.cameras, [view])
            panels.append(render_image(rec.density.cpu(), rec.grid, cams, step=rec.setup.step)[0].cpu())
        strip = torch.cat([p.mean(0) for p in panels], 1).clamp(0, 1).numpy()
        name = folder / f"frame_{frame:03d}_{rec0.scene.views[view]}.png"
        cv2.imwrite(str(name), (strip * 255).astype(np.uint8))
        print(f"wrote {name}: captured, " + ", ".join(label for label, _ in entries))


if __name__ == "__main__":
    sys.exit(main())
