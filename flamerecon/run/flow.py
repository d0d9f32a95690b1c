"""The flow of a reconstructed sequence written where its frames are: a multirun over frames
(``python train.py -m scene.frame=...``) gets a ``velocity.npz`` in each frame's run folder but
the last, then its sequence files again with the velocities (``sequence.npz``, the ``.pvd``
series with vectors), ``flow.json`` (the options and every pair's record), TensorBoard scalars
in ``flow/`` (``flow/mean_speed`` in world units per second, ``flow/relative_divergence``,
``flow/residual`` and ``flow/residual_none``: the transport residual of the next frame's images
with and without the motion, ``flow/seconds``; step = frame) and figures in ``flow_figures/``.

Frames are read one at a time (:func:`~flamerecon.run.folder.load_run`), frame t+1's operator
built again (:func:`~flamerecon.fit.build.build`) to fit u_t to its images, warm-started from
u_{t-1}: memory holds two frames.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import yaml

from flamerecon.dynamics.conventions import frame_rate_of, speed_unit, up_of
from flamerecon.dynamics.flow import FlowOptions, cells_to_world, estimate_velocity, flow_statistics
from flamerecon.dynamics.sequence import FrameFacts, check_sequence
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.fit.build import build
from flamerecon.outputs.atomic import make_folder, write_json_atomic
from flamerecon.outputs.export import DENSITY_FILE, load_density
from flamerecon.outputs.figures import write_png
from flamerecon.outputs.flow_figures import streamlines_figure, velocity_slices_figure
from flamerecon.outputs.sequence import assemble_sweep, find_frame_runs
from flamerecon.outputs.velocity import VELOCITY_FILE, save_velocity
from flamerecon.progress import Progress
from flamerecon.run.folder import load_run
from flamerecon.run.tensorboard import RunWriter

FLOW_JSON = "flow.json"
FIGURES = "flow_figures"


def section_options(kind: type, section: str, overrides: list[str]):
    """Options ``kind`` (a dataclass) from command-line ``SECTION.KEY=VALUE`` overrides (values
    read as YAML), each checked by its rule."""
    known = list(kind.__dataclass_fields__)
    values = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        name = key.removeprefix(f"{section}.")
        if not sep or not key.startswith(f"{section}.") or name not in known:
            raise ArgumentError(f"{item}: not a {section} option; give {section}.KEY=VALUE with KEY one of {known}")
        values[name] = yaml.safe_load(text)
    return kind(**values)


def flow_options(overrides: list[str]) -> FlowOptions:
    """:class:`~flamerecon.dynamics.flow.FlowOptions` from command-line ``flow.KEY=VALUE`` overrides."""
    return section_options(FlowOptions, "flow", overrides)


def parse_with_overrides(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``parser.parse_args`` where a KEY=VALUE override may follow an option that takes a list
    (``--horizons 1 5 scene=plume``: horizons 1 and 5, then the override, as ``--help`` shows
    them): every positional argument is moved after ``--``, in its order, so that no list
    option swallows one."""
    argv = sys.argv[1:] if argv is None else list(argv)
    options, positional, index = [], [], 0
    while index < len(argv):
        item = argv[index]
        index += 1
        if item == "--":
            positional += argv[index:]
            break
        action = parser._option_string_actions.get(item.split("=", 1)[0]) if item.startswith("-") else None
        if action is None:
            (options if item.startswith("-") else positional).append(item)
            continue
        options.append(item)
        if "=" in item or action.nargs == 0:
            continue
        if action.nargs is None or isinstance(action.nargs, int):  # a fixed number of values
            count = 1 if action.nargs is None else action.nargs
            options += argv[index:index + count]
            index += count
            continue
        while index < len(argv) and not argv[index].startswith("-") and "=" not in argv[index]:
            options.append(argv[index])  # a list's values: up to an option or an override
            index += 1
    return parser.parse_args([*options, "--", *positional] if positional else options)


def flow_sweep(sweep_dir: str | os.PathLike, options: FlowOptions | None = None, figures: list[int] | None = None,
               vti: bool = True, device: str = "auto") -> dict:
    """Fit and write the velocities of the sweep in ``sweep_dir`` (module doc); ``figures``: the
    frames to draw (default: the middle pair's first frame; [] none). Returns flow.json's
    content."""
    options = options or FlowOptions()
    sweep_dir = Path(sweep_dir)
    runs = find_frame_runs(sweep_dir)
    frames = [r.frame for r in runs]
    check_sequence([run_facts(r.run_dir, r.frame) for r in runs], str(sweep_dir))
    figures = [frames[(len(frames) - 1) // 2]] if figures is None else list(figures)
    missing = [f for f in figures if f not in frames[:-1]]
    if missing:
        raise ConfigError(f"figures: frames {missing} have no velocity; choose among {frames[:-1]}")
    previous = load_run(runs[0].run_dir, device)
    rate = frame_rate_of(previous.scene, options.frame_rate)
    if rate is None:
        raise ConfigError(f"flow.frame_rate: {previous.folder}'s scene does not say its frame rate; give "
                          "flow.frame_rate=FRAMES_PER_SECOND")
    up = up_of(previous.scene, options.up)
    unit = speed_unit(previous.scene)
    print(f"flow: {len(frames)} frames at {rate:g} frames per second, up {up}, velocities in {unit}", flush=True)
    writer = RunWriter(str(sweep_dir / "flow"))
    progress = Progress("flow", len(runs) - 1, "frame pair")
    records, control = [], None
    try:
        for n, run in enumerate(runs[1:], 1):
            current = load_run(run.run_dir, device)
            setup = build(current.scene, current.options, current.density.device, current.grid)
            pair = estimate_velocity(previous.density, setup, options, control, frames[n - 1])
            control = pair.control if options.warm_start else None
            world = cells_to_world(pair.u, previous.grid, float(rate))
            record = {**pair.record(), "next_frame": frames[n], "frame_rate": float(rate),
                      "mean_speed_world": flow_statistics(world, previous.density, options, up)[1]}
            save_velocity(previous.folder / VELOCITY_FILE, world.cpu().numpy(), previous.grid.bbox_min,
                          previous.grid.bbox_max, frames[n - 1], float(rate), {**record, "options": options.as_dict()})
            writer.scalars(frames[n - 1], {"mean_speed": record["mean_speed_world"],
                                           "relative_divergence": pair.relative_divergence,
                                           "residual": pair.residual, "residual_none": pair.residual_none,
                                           "seconds": pair.seconds}, "flow")
            if frames[n - 1] in figures:
                folder = make_folder(sweep_dir / FIGURES)
                density = previous.density.cpu().numpy()
                velocity = world.cpu().numpy()
                title = f"frame {frames[n - 1]} -> {frames[n]} ({unit})"
                box, length = (previous.grid.bbox_min, previous.grid.bbox_max), unit.removesuffix("/s")
                write_png(folder / f"velocity_slices_{frames[n - 1]:04d}.png",
                          velocity_slices_figure(density, velocity, *box, title, length, up=up))
                write_png(folder / f"streamlines_{frames[n - 1]:04d}.png",
                          streamlines_figure(density, velocity, *box, title, length, up=up))
            records.append(record)
            progress.update(n, f"frame {frames[n - 1]}: residual {pair.residual_none:.4f} -> {pair.residual:.4f}")
            previous = current
            del setup
    finally:
        writer.close()
    report = {"options": options.as_dict(), "units": f"velocity.npz: world units per second (x, y, z); {unit}",
              "frame_rate": float(rate), "up": up, "pairs": records}
    write_json_atomic(sweep_dir / FLOW_JSON, report)
    assemble_sweep(sweep_dir, vti=vti)
    return report


def run_facts(run_dir: Path, frame: int) -> FrameFacts:
    """What a run folder's ``density.npz`` says of its frame (its box, grid, channels and the
    cameras it was fitted to), read without building anything."""
    saved = load_density(Path(run_dir) / DENSITY_FILE)
    return FrameFacts(f"frame {frame} ({run_dir})", frame, tuple(saved.bbox_min.tolist()),
                      tuple(saved.bbox_max.tolist()), tuple(saved.density.shape[1:]), int(saved.density.shape[0]),
                      tuple(saved.views))
