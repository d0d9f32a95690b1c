"""What limits a held-out view: the run's score beside what would be gained by knowing what the
training views cannot tell (diagnosis only: these oracles use the held-out image, so they never
choose a setting).

    python scripts/heldout_limits.py --frames 25,65 [scene=scalarflow by default, train.py overrides ...]

Per frame and held-out view, in dB: the run's PSNR; with the view's own least-squares gain
(its exposure); with the render blurred by the Gaussian (0.5-3 px) that suits it best (a
smoother prediction); with the view's pose refitted to its own image against the run's density
(its calibration relative to the refined training cameras; Levenberg-Marquardt, 10 iterations).
Then the detail correlation (README, Scores): the run's, at the best whole-pixel shift of the
render (up to 3 px each way: how much a misregistration costs the fine band), with the pose
refitted, and the ratio of the render's detail-band amplitude (std) to the capture's (how much
fine structure the render has at all, in or out of place). ``--pictures DIR`` writes
DIR/<frame>-<view>.png: captured | rendered over their detail bands.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import math
import sys
from pathlib import Path

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import cv2
import kornia
import torch

import flamerecon as fr
from flamerecon.evaluate.metrics import detail_band, detail_correlation
from flamerecon.evaluate.scores import detail_sigma
from flamerecon.fit.build import scene_masks
from flamerecon.fit.pose_uncertainty import measure_offset
from flamerecon.fit.refine_cameras import RefineOptions, corrected_cameras
from flamerecon.geometry.cameras import camera_subset
from flamerecon.run.cli import compose_train, frame_list, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene

BLURS = (0.5, 1.0, 1.5, 2.0, 3.0)
SHIFT_PX = 3


def shifted_detail(rendered: torch.Tensor, captured: torch.Tensor, sigma: float) -> float:
    """The best detail correlation of the render (C, H, W) moved by whole pixels (at most
    :data:`SHIFT_PX` each way), both cropped by that margin so no wrapped pixel counts."""
    m = SHIFT_PX
    crop = (slice(None), slice(m, -m), slice(m, -m))
    return max(detail_correlation(torch.roll(rendered, (dy, dx), (-2, -1))[crop], captured[crop], sigma)
               for dy in range(-m, m + 1) for dx in range(-m, m + 1))


def band_ratio(rendered: torch.Tensor, captured: torch.Tensor, sigma: float) -> float:
    return float(detail_band(rendered.clamp(0, 1), sigma).std() / detail_band(captured, sigma).std())


def picture(path: Path, rendered: torch.Tensor, captured: torch.Tensor, sigma: float) -> None:
    """captured | rendered (gray, the capture's range) over their detail bands (mid-gray 0)."""
    hi = float(captured.max()) or 1.0
    bands = [detail_band(x.clamp(0, 1), sigma).mean(0) for x in (captured, rendered)]
    half = 0.5 * float(bands[0].abs().max()) or 1.0
    top = torch.cat([captured.mean(0) / hi, rendered.clamp(0, 1).mean(0) / hi], 1)
    bottom = torch.cat([b / (2 * half) + 0.5 for b in bands], 1)
    image = (torch.cat([top, bottom], 0).clamp(0, 1) * 255).round().byte().numpy()
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def psnr(rendered: torch.Tensor, captured: torch.Tensor) -> float:
    return 10.0 * math.log10(1.0 / float(((rendered.double() - captured.double()) ** 2).mean()))


def best_gain(rendered: torch.Tensor, captured: torch.Tensor) -> float:
    return float((rendered * captured).sum() / (rendered * rendered).sum().clamp_min(1e-30))


def refit_pose(rec, view: int) -> torch.Tensor:
    """The held-out camera ``view`` with its pose fitted to its own image against the run's
    density (:func:`~flamerecon.fit.pose_uncertainty.measure_offset`); returns its render
    (1, C, H, W)."""
    scene, grid = rec.scene, rec.grid
    cam = camera_subset(scene.cameras, [view])
    pivot = 0.5 * (grid.lo() + grid.hi())
    masks = scene_masks(scene, scene.images, rec.options)
    found = measure_offset([rec.density.cpu()], grid, cam, [scene.images[view]], [masks[view]], rec.setup.step,
                           pivot, RefineOptions(refine="pose", max_rays=40000), "its own image")
    return fr.render(rec.density.cpu(), grid, corrected_cameras(cam, found.theta[None].float(), pivot),
                     rec.setup.step)


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    parser.add_argument("--frames", type=frame_list, required=True, help="comma-separated scene.frame values")
    parser.add_argument("--pictures", type=Path, help="folder for <frame>-<view>.png (captured | rendered, "
                        "over their detail bands)")
    args = parser.parse_args(argv)

    def run() -> None:
        print(f"{'frame':>5} {'view':<10} {'run':>6} {'+gain':>6} {'+blur':>6} {'+pose':>6} {'detail':>7} "
              f"{'+shift':>7} {'+pose':>7} {'band':>6}   (dB, then the detail correlation and the band "
              "amplitude ratio; every column after 'run' and 'detail' uses the held-out image)", flush=True)
        if args.pictures:
            args.pictures.mkdir(parents=True, exist_ok=True)
        for frame in args.frames:
            cfg = compose_train([*args.overrides, f"scene.frame={frame}"])
            options = options_from_config(cfg)
            scene = load_scene(cfg.scene)
            rec = fr.reconstruct(scene, options)
            train = [scene.views[v] for v in rec.setup.train]
            for v in rec.setup.holdout:
                name = scene.views[v]
                captured = scene.images[v:v + 1]
                rendered = fr.render(rec.density.cpu(), rec.grid, camera_subset(rec.scene.cameras, [v]),
                                     rec.setup.step)
                gained = psnr(rendered * best_gain(rendered, captured), captured)
                blurred = max(psnr(kornia.filters.gaussian_blur2d(rendered, (2 * math.ceil(3 * s) + 1,) * 2,
                                                                   (s, s)), captured) for s in BLURS)
                posed_image = refit_pose(rec, v)
                posed = psnr(posed_image, captured)
                sigma = detail_sigma(scene)
                details = (detail_correlation(rendered[0], captured[0], sigma),
                           shifted_detail(rendered[0], captured[0], sigma),
                           detail_correlation(posed_image[0], captured[0], sigma),
                           band_ratio(rendered[0], captured[0], sigma))
                print(f"{frame:5d} {name:<10} {psnr(rendered, captured):6.2f} {gained:6.2f} {blurred:6.2f} "
                      f"{posed:6.2f} {details[0]:7.3f} {details[1]:7.3f} {details[2]:7.3f} {details[3]:6.3f}"
                      f"   (fitted to {train})", flush=True)
                if args.pictures:
                    picture(args.pictures / f"{frame}-{name}.png", rendered[0], captured[0], sigma)

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
