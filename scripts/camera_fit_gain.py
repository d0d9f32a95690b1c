"""How much a camera fit's first round lowers its residual, on exact cameras and on cameras off by
a known amount: the measurement behind ``calibration.min_gain`` (docs/results.md, "Any rig").

    python scripts/camera_fit_gain.py [--sizes 64x48:20:40,64x48:32:100,96x72:32:100]

For each size (image WxH, grid cells, solver iterations) the synthetic flame's 6 cameras (one
held out) are fitted once with their exact calibration and once with every training camera turned
by 0.1 and by 0.5 degrees about a random axis, moved by 0.2% and 1% of its distance, its principal
point by 0.5 and 2 px (the part common to all cameras, which no image can see, removed); one round
of ``calibration.refine=pose``. Prints the relative drop of the fit's residual RMS in that round.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import math
import sys
from dataclasses import replace

import flamerecon  # noqa: F401 (first: its OpenMP setting is read when torch loads)

# isort: split

import torch

import flamerecon as fr
from flamerecon.fit.reconstruct import calibrated_scene
from flamerecon.fit.refine_cameras import (
    N_PARAMS,
    RefineOptions,
    corrected_cameras,
    gauge_basis,
    round_gain,
    skew,
    with_cameras,
)
from flamerecon.geometry.cameras import camera_centers, camera_subset
from flamerecon.geometry.grid import VoxelGrid
from flamerecon.run.cli import run_script, script_parser

#: (degrees, fraction of the distance, pixels) of the two miscalibrations
ERRORS = ((0.1, 0.002, 0.5), (0.5, 0.01, 2.0))


def offsets(cams, pivot: torch.Tensor, degrees: float, fraction: float, pixels: float, seed: int = 1) -> torch.Tensor:
    """Corrections theta (T, 9) of that size per camera (random axes and directions), less the
    part common to every camera (:func:`~flamerecon.fit.refine_cameras.gauge_basis`)."""
    g = torch.Generator().manual_seed(seed)
    T = cams.batch_size
    unit = torch.nn.functional.normalize(torch.randn(2, T, 3, generator=g), dim=-1)
    theta = torch.zeros(T, N_PARAMS)
    theta[:, :3] = unit[0] * math.radians(degrees)
    c = camera_centers(cams)
    R = torch.linalg.matrix_exp(skew(theta[:, :3]))
    moved = c + unit[1] * fraction * (c - pivot).norm(dim=-1, keepdim=True)
    theta[:, 3:6] = moved - pivot - (R @ (c - pivot)[..., None]).squeeze(-1)
    angle = torch.rand(T, generator=g) * 2 * math.pi
    theta[:, 7], theta[:, 8] = pixels * torch.cos(angle), pixels * torch.sin(angle)
    basis = gauge_basis(cams, pivot, torch.ones(T, N_PARAMS, dtype=torch.float64), list(range(N_PARAMS)))
    return (basis @ (basis.T @ theta.double().reshape(-1))).reshape(T, N_PARAMS).float()


def first_round_gain(scene, options) -> float:
    _, record = calibrated_scene(scene, options, torch.device("cpu"))
    return round_gain(record["rounds"][0])


def measure(width: int, height: int, cells: int, iterations: int) -> list[float]:
    scene = fr.load_scene("synthetic", n_cameras=6, width=width, height=height, phantom_resolution=48)
    options = fr.ReconstructionOptions(grid=fr.GridOptions(resolution=cells), device="cpu",
                                       solver=fr.SolverOptions().with_values(max_iters=iterations),
                                       calibration=RefineOptions(refine="pose", rounds=1, iterations=2, min_gain=0.0))
    train, _ = scene.split(None)
    grid = VoxelGrid.from_box(scene.bbox_min, scene.bbox_max, cells)
    pivot = 0.5 * (grid.lo() + grid.hi())
    exact = camera_subset(scene.cameras, train)
    gains = [first_round_gain(scene, options)]
    for size in ERRORS:
        off = with_cameras(scene.cameras, train, corrected_cameras(exact, offsets(exact, pivot, *size), pivot))
        gains.append(first_round_gain(replace(scene, cameras=off), options))
    return gains


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--sizes", default="64x48:20:40,64x48:32:100,96x72:32:100",
                        help="comma-separated WxH:CELLS:ITERATIONS")
    args = parser.parse_args(argv)

    def run() -> None:
        print(f"{'images':>8} {'grid':>5} {'iters':>5} {'exact':>8} "
              + " ".join(f"{f'{d:g} deg {p:g} px':>14}" for d, _, p in ERRORS))
        for spec in args.sizes.split(","):
            try:
                size, cells, iterations = spec.split(":")
                width, height = (int(n) for n in size.split("x"))
                cells, iterations = int(cells), int(iterations)
            except ValueError:
                raise ValueError(f"--sizes: '{spec}' is not WxH:CELLS:ITERATIONS") from None
            gains = measure(width, height, cells, iterations)
            print(f"{size:>8} {cells:5d} {iterations:5d} {100 * gains[0]:7.2f}% "
                  + " ".join(f"{100 * g:13.2f}%" for g in gains[1:]), flush=True)

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
