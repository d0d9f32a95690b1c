"""What limits a held-out view: the run's score beside what would be gained by knowing what the
training views cannot tell (diagnosis only: these oracles use the held-out image, so they never
choose a setting).

    python scripts/heldout_limits.py --frames 25,65 [scene=scalarflow by default, train.py overrides ...]

Per frame and held-out view, in dB: the run's PSNR; with the view's own least-squares gain
(its exposure); with the render blurred by the Gaussian (0.5-3 px) that suits it best (a
smoother prediction); with the view's pose refitted to its own image against the run's density
(its calibration relative to the refined training cameras; Levenberg-Marquardt, 10 iterations).
"""

from __future__ import annotations

import math
import sys

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import kornia
import torch

import flamerecon as fr
from flamerecon.fit.build import scene_masks
from flamerecon.fit.refine_cameras import (
    CameraFit,
    RefineOptions,
    camera_step,
    corrected_cameras,
    fit_pixels,
    prior_sizes,
)
from flamerecon.geometry.cameras import camera_subset
from flamerecon.run.cli import compose_train, frame_list, run_script, script_parser
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene

BLURS = (0.5, 1.0, 1.5, 2.0, 3.0)


def psnr(rendered: torch.Tensor, captured: torch.Tensor) -> float:
    return 10.0 * math.log10(1.0 / float(((rendered.double() - captured.double()) ** 2).mean()))


def best_gain(rendered: torch.Tensor, captured: torch.Tensor) -> float:
    return float((rendered * captured).sum() / (rendered * rendered).sum().clamp_min(1e-30))


def refit_pose(rec, view: int, iterations: int = 10) -> torch.Tensor:
    """The held-out camera ``view`` with its pose fitted to its own image against the run's
    density; returns its render (1, C, H, W)."""
    scene, grid = rec.scene, rec.grid
    cam = camera_subset(scene.cameras, [view])
    image = scene.images[view:view + 1]
    options = RefineOptions(refine="pose", max_rays=40000)
    pivot = 0.5 * (grid.lo() + grid.hi())
    masks = scene_masks(scene, scene.images, rec.options)[view:view + 1]
    index, valid = fit_pixels(masks, options.band_px, options.max_rays, torch.Generator().manual_seed(0))
    fit = CameraFit([rec.density.cpu()], grid, cam, pivot, image, index, valid, rec.setup.step)
    basis = torch.eye(9, dtype=torch.float64)[:, :6]  # one camera: no gauge to hold
    theta, _ = camera_step(fit, torch.zeros(1, 9), prior_sizes(cam, pivot, options), basis, list(range(6)),
                           iterations)
    return fr.render(rec.density.cpu(), grid, corrected_cameras(cam, theta, pivot), rec.setup.step)


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    parser.add_argument("--frames", type=frame_list, required=True, help="comma-separated scene.frame values")
    args = parser.parse_args(argv)

    def run() -> None:
        print(f"{'frame':>5} {'view':<10} {'run':>6} {'+gain':>6} {'+blur':>6} {'+pose':>6}"
              "   (dB; every column after 'run' uses the held-out image)", flush=True)
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
                posed = psnr(refit_pose(rec, v), captured)
                print(f"{frame:5d} {name:<10} {psnr(rendered, captured):6.2f} {gained:6.2f} {blurred:6.2f} "
                      f"{posed:6.2f}   (fitted to {train})", flush=True)

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
