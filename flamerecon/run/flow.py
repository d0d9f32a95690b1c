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

import os
from itertools import pairwise
from pathlib import Path

import yaml

from flamerecon.dynamics.conventions import up_of
from flamerecon.dynamics.flow import FlowOptions, cells_to_world, estimate_velocity, flow_statistics
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.fit.build import build
from flamerecon.outputs.atomic import make_folder, write_json_atomic
from flamerecon.outputs.figures import write_png
from flamerecon.outputs.flow_figures import length_unit, streamlines_figure, velocity_slices_figure
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


def overrides_last(argv: list[str], options: tuple[str, ...]) -> list[str]:
    """``argv`` with every KEY=VALUE override that follows one of ``options`` (which take a
    list of values, e.g. ``--horizons 1 2 5``) moved to the end, where argparse reads overrides:
    ``--horizons 1 5 scene=plume`` is horizons 1 and 5 and the override scene=plume."""
    out, moved, inside = [], [], False
    for item in argv:
        if item.startswith("-"):
            inside = item.split("=", 1)[0] in options
        elif inside and "=" in item:
            moved.append(item)
            continue
        out.append(item)
    return out + moved


def flow_sweep(sweep_dir: str | os.PathLike, options: FlowOptions | None = None, figures: list[int] | None = None,
               vti: bool = True, device: str = "auto") -> dict:
    """Fit and write the velocities of the sweep in ``sweep_dir`` (module doc); ``figures``: the
    frames to draw (default: the middle pair's first frame; [] none). Returns flow.json's
    content."""
    options = options or FlowOptions()
    sweep_dir = Path(sweep_dir)
    runs = find_frame_runs(sweep_dir)
    frames = [r.frame for r in runs]
    if len(runs) < 2:
        raise ConfigError(f"{sweep_dir}: a flow needs at least two frames; it holds {frames}")
    gaps = [f"{a}-{b}" for a, b in pairwise(frames) if b != a + 1]
    if gaps:
        raise ConfigError(f"{sweep_dir}: frames {frames} are not consecutive (gaps {gaps}); a velocity carries "
                          "one frame onto the next: reconstruct every frame of the stretch")
    figures = [frames[(len(frames) - 1) // 2]] if figures is None else list(figures)
    missing = [f for f in figures if f not in frames[:-1]]
    if missing:
        raise ConfigError(f"figures: frames {missing} have no velocity; choose among {frames[:-1]}")
    writer = RunWriter(str(sweep_dir / "flow"))
    progress = Progress("flow", len(runs) - 1, "frame pair")
    records, previous, control = [], load_run(runs[0].run_dir, device), None
    try:
        for n, run in enumerate(runs[1:], 1):
            current = load_run(run.run_dir, device)
            rate = options.frame_rate or previous.scene.meta.get("frame_rate")
            if rate is None:
                raise ConfigError(f"flow.frame_rate: {previous.folder}'s scene does not say its frame rate; give "
                                  "flow.frame_rate=FRAMES_PER_SECOND")
            setup = build(current.scene, current.options, current.density.device, current.grid)
            pair = estimate_velocity(previous.density, setup, options, control, frames[n - 1])
            control = pair.control if options.warm_start else None
            world = cells_to_world(pair.u, previous.grid, float(rate))
            record = {**pair.record(), "next_frame": frames[n], "frame_rate": float(rate),
                      "mean_speed_world": flow_statistics(world, previous.density, options,
                                                          up_of(previous.scene, options.up))[1]}
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
                title, unit = f"frame {frames[n - 1]} -> {frames[n]}", length_unit(previous.scene.name)
                box = (previous.grid.bbox_min, previous.grid.bbox_max)
                write_png(folder / f"velocity_slices_{frames[n - 1]:04d}.png",
                          velocity_slices_figure(density, velocity, *box, title, unit))
                write_png(folder / f"streamlines_{frames[n - 1]:04d}.png",
                          streamlines_figure(density, velocity, *box, title, unit))
            records.append(record)
            progress.update(n, f"frame {frames[n - 1]}: residual {pair.residual_none:.4f} -> {pair.residual:.4f}")
            previous = current
            del setup
    finally:
        writer.close()
    report = {"options": options.as_dict(), "units": "velocity.npz: world units per second (x, y, z)",
              "pairs": records}
    write_json_atomic(sweep_dir / FLOW_JSON, report)
    assemble_sweep(sweep_dir, vti=vti)
    return report
