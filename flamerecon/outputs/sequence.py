"""A flame video as a sequence of per-frame runs: gather a Hydra multirun into one series.

A sweep folder (``python train.py -m scene.frame=...``) holds one run folder per job
(``0/``, ``1/``, ...), each with ``density.npz``, maybe ``metrics.json`` and
``.hydra/{config,overrides}.yaml``. :func:`assemble_sweep` writes into the sweep folder:

- ``sequence.npz``: ``density`` float32 (T, C, nz, ny, nx), ``frames`` (T,) int64, ``bbox_min``,
  ``bbox_max`` (3,), ``views`` (T, V) names, ``run_dirs`` (T,) job folder names;
  frames in increasing order, streamed one frame at a time (memory: one frame);
- ``sequence.pvd`` + ``sequence_vti/frame_NNNN.vti``: the series for ParaView (time = frame);
- ``sequence_metrics.csv`` (one row per frame, nested metrics flattened to dotted names) and
  ``sequence_metrics.png`` when matplotlib is installed.
"""

from __future__ import annotations

import csv
import io
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from flamerecon.outputs.atomic import atomic_path
from flamerecon.outputs.export import DENSITY_FILE, Density, load_density, write_pvd, write_vti
from flamerecon.plain import json_value

SEQUENCE_FILE = "sequence.npz"
PVD_FILE = "sequence.pvd"
VTI_FOLDER = "sequence_vti"
METRICS_CSV = "sequence_metrics.csv"
METRICS_PNG = "sequence_metrics.png"
# metric names plotted first, when present (leaf names of the flattened metrics.json)
_PLOT_FIRST = ("psnr", "ssim", "detail", "rel_l2", "iou", "iterations", "seconds", "objective")
_MAX_PANELS = 6
#: axis labels with units of the metrics plotted
_UNITS = {"psnr": "PSNR [dB]", "ssim": "SSIM", "detail": "detail correlation", "rel_l2": "relative L2 error",
          "iou": "support IoU", "iterations": "iterations", "seconds": "seconds [s]", "objective": "objective"}


class SweepError(ValueError):
    """A sweep folder whose runs cannot be put together (names the run folder and what is wrong)."""


@dataclass
class FrameRun:
    """One job of the sweep: its folder, frame number and flattened metrics."""

    run_dir: Path
    frame: int
    metrics: dict[str, Any] = field(default_factory=dict)


def frame_number(run_dir: str | os.PathLike) -> int | None:
    """The frame a run reconstructed: ``scene.frame`` from ``.hydra/config.yaml``, else the
    ``scene.frame=N`` override in ``.hydra/overrides.yaml``, else a ``frame`` field stored in
    ``density.npz``; None when none of them says."""
    run_dir = Path(run_dir)
    config = run_dir / ".hydra" / "config.yaml"
    if config.is_file():
        cfg = _read_yaml(config)
        scene = cfg.get("scene") if isinstance(cfg, dict) else None
        if isinstance(scene, dict) and scene.get("frame") is not None:
            return _as_frame(scene["frame"], config, "scene.frame")
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if overrides.is_file():
        for item in _read_yaml(overrides) or []:
            key, _, value = str(item).partition("=")
            if key.lstrip("+~") == "scene.frame" and value:
                return _as_frame(value, overrides, "scene.frame")
    density = run_dir / DENSITY_FILE
    if density.is_file():
        with np.load(density, allow_pickle=False) as f:
            if "frame" in f.files:
                return _as_frame(f["frame"], density, "frame")
    return None


def find_frame_runs(sweep_dir: str | os.PathLike, skip_incomplete: bool = False) -> list[FrameRun]:
    """The sweep's run folders (subfolders holding ``density.npz`` or ``.hydra/``), sorted by frame.

    A run without ``density.npz`` (a failed or unfinished job) is an error, or skipped with
    ``skip_incomplete``. Runs that do not say their frame are numbered by their job folder,
    but only when none of them says it.
    """
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"{sweep_dir}: no such sweep folder")
    candidates = [
        d for d in sweep_dir.iterdir()
        if d.is_dir() and ((d / DENSITY_FILE).is_file() or (d / ".hydra").is_dir())
    ]
    incomplete = sorted(str(d) for d in candidates if not (d / DENSITY_FILE).is_file())
    if incomplete and not skip_incomplete:
        raise SweepError(f"{sweep_dir}: runs without {DENSITY_FILE}: {incomplete}")
    runs_dirs = sorted((d for d in candidates if (d / DENSITY_FILE).is_file()), key=_job_order)
    if not runs_dirs:
        raise SweepError(f"{sweep_dir}: no run folder with {DENSITY_FILE}")
    frames = [frame_number(d) for d in runs_dirs]
    if all(f is None for f in frames):
        frames = list(range(len(runs_dirs)))
    elif any(f is None for f in frames):
        unknown = [str(d) for d, f in zip(runs_dirs, frames) if f is None]
        raise SweepError(f"{sweep_dir}: runs that do not say their scene.frame: {unknown}")
    seen: dict[int, Path] = {}
    for d, f in zip(runs_dirs, frames):
        if f in seen:
            raise SweepError(f"{sweep_dir}: frame {f} reconstructed twice, in {seen[f]} and {d}")
        seen[f] = d
    runs = [FrameRun(d, f, _read_metrics(d)) for d, f in zip(runs_dirs, frames)]
    return sorted(runs, key=lambda r: r.frame)


def write_sequence_npz(path: str | os.PathLike, runs: list[FrameRun]) -> Path:
    """Stack the runs' densities into ``sequence.npz`` (see module doc), one frame in memory at
    a time. All runs must share the volume shape and bounding box."""
    first = load_density(runs[0].run_dir)
    shape = (len(runs), *first.density.shape)
    views = [first.views]
    path = Path(path)
    with atomic_path(path) as tmp, zipfile.ZipFile(
        tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True
    ) as archive:
        with archive.open("density.npy", "w", force_zip64=True) as member:
            header = {"descr": np.dtype("<f4").str, "fortran_order": False, "shape": shape}
            np.lib.format.write_array_header_2_0(member, header)
            for index, run in enumerate(runs):
                volume = first if index == 0 else load_density(run.run_dir)
                _check_same_grid(run.run_dir, volume, first, runs[0].run_dir)
                if index:
                    views.append(volume.views)
                member.write(np.ascontiguousarray(volume.density, dtype="<f4").tobytes())
        width = max((len(v) for v in views), default=0)
        small = {
            "frames": np.array([r.frame for r in runs], dtype=np.int64),
            "bbox_min": first.bbox_min,
            "bbox_max": first.bbox_max,
            "views": np.array([v + [""] * (width - len(v)) for v in views], dtype=np.str_)
            .reshape(len(runs), width),
            "run_dirs": np.array([r.run_dir.name for r in runs], dtype=np.str_),
        }
        for name, array in small.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, array, allow_pickle=False)
            archive.writestr(name + ".npy", buffer.getvalue())
    return path


def write_vti_series(sweep_dir: str | os.PathLike, runs: list[FrameRun]) -> Path:
    """``sequence_vti/frame_NNNN.vti`` per run and the ``sequence.pvd`` index (time = frame)."""
    sweep_dir = Path(sweep_dir)
    folder = sweep_dir / VTI_FOLDER
    folder.mkdir(exist_ok=True)
    entries = []
    for run in runs:
        volume = load_density(run.run_dir)
        file = folder / f"frame_{run.frame:04d}.vti"
        write_vti(file, volume.density, volume.bbox_min, volume.bbox_max)
        entries.append((run.frame, file.relative_to(sweep_dir)))
    return write_pvd(sweep_dir / PVD_FILE, entries)


def write_metrics_csv(path: str | os.PathLike, runs: list[FrameRun]) -> Path:
    """One row per frame: ``frame``, ``run_dir``, then every flattened metric (sorted names);
    a metric a run lacks is left empty."""
    names = sorted({k for r in runs for k in r.metrics})
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["frame", "run_dir", *names])
    for r in runs:
        writer.writerow([r.frame, r.run_dir.name, *(r.metrics.get(n, "") for n in names)])
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(buffer.getvalue())
    return path


def plot_metrics(path: str | os.PathLike, runs: list[FrameRun]) -> Path | None:
    """Numeric metrics against frame, one panel per metric name (``psnr``, ``ssim``, ... first),
    one line per place it was measured (e.g. each held-out view), the PSNR panel with each
    view's black-image floor dashed, axes with units, legends beside the panels, a title naming
    the sweep. None without matplotlib or without numeric metrics."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return None
    groups: dict[str, list[str]] = {}
    numeric = {k for r in runs for k, v in r.metrics.items() if _is_number(v)}
    for name in sorted(numeric):
        if name.rsplit(".", 1)[-1].startswith("psnr_black"):
            continue  # drawn as the floor under its PSNR
        groups.setdefault(name.rsplit(".", 1)[-1], []).append(name)
    if not groups:
        return None
    order = sorted(groups, key=lambda g: (_PLOT_FIRST.index(g) if g in _PLOT_FIRST else 99, g))
    order = order[:_MAX_PANELS]
    fig = Figure(figsize=(6.2 * min(len(order), 3), 3.4 * ((len(order) + 2) // 3) + 0.5), dpi=100,
                 layout="constrained")
    frames = np.array([r.frame for r in runs])

    def series(name: str) -> np.ndarray:
        return np.array([float(r.metrics[name]) if _is_number(r.metrics.get(name)) else np.nan for r in runs])

    for panel, group in enumerate(order, start=1):
        ax = fig.add_subplot((len(order) + 2) // 3, min(len(order), 3), panel)
        for name in groups[group]:
            label = name[: -len(group) - 1] if name != group else group
            line, = ax.plot(frames, series(name), marker="o", label=label)
            if group == "psnr" and f"{name}_black" in numeric:
                ax.plot(frames, series(f"{name}_black"), linestyle="--", color=line.get_color(),
                        label=f"{label}: black image")
        ax.set_xlabel("frame")
        ax.set_ylabel(_UNITS.get(group, group))
        ax.set_title(group if len(groups[group]) > 1 else groups[group][0], fontsize="medium")
        if len(ax.get_lines()) > 1:
            ax.legend(fontsize="x-small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
        ax.grid(alpha=0.3)
    fig.suptitle(f"scores per frame of {Path(path).parent.name or Path(path).parent} "
                 "(held-out: predictions; train: the fit; dashed: an all-black image)")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def assemble_sweep(
    sweep_dir: str | os.PathLike, vti: bool = True, skip_incomplete: bool = False
) -> dict[str, Path | None]:
    """Write the sequence files into ``sweep_dir``; returns what was written by kind
    (``npz``, ``pvd``, ``csv``, ``png``; ``png`` None when matplotlib is absent)."""
    sweep_dir = Path(sweep_dir)
    runs = find_frame_runs(sweep_dir, skip_incomplete=skip_incomplete)
    written: dict[str, Path | None] = {"npz": write_sequence_npz(sweep_dir / SEQUENCE_FILE, runs)}
    if vti:
        written["pvd"] = write_vti_series(sweep_dir, runs)
    written["csv"] = write_metrics_csv(sweep_dir / METRICS_CSV, runs)
    written["png"] = plot_metrics(sweep_dir / METRICS_PNG, runs)
    return written


def flatten_metrics(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts and lists to ``{"a.b.0": scalar}``; keeps numbers, strings and booleans."""
    flat: dict[str, Any] = {}
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    else:
        if isinstance(obj, (int, float, str, bool)) or obj is None:
            flat[prefix] = obj
        return flat
    for key, value in items:
        flat.update(flatten_metrics(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _read_metrics(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "metrics.json"
    if not path.is_file():
        return {}
    try:
        return flatten_metrics(json_value(path.read_text()))
    except ValueError as err:
        raise SweepError(f"{path}: not valid JSON ({err})") from err


def _check_same_grid(run_dir: Path, volume: Density, first: Density, first_dir: Path) -> None:
    if volume.density.shape != first.density.shape:
        raise SweepError(
            f"{run_dir / DENSITY_FILE}: field 'density' has shape {volume.density.shape}, "
            f"{first_dir / DENSITY_FILE} has {first.density.shape}"
        )
    for name in ("bbox_min", "bbox_max"):
        a, b = getattr(volume, name), getattr(first, name)
        if not np.allclose(a, b, rtol=1e-6, atol=1e-9):
            raise SweepError(
                f"{run_dir / DENSITY_FILE}: field '{name}' {a} differs from {first_dir}'s {b}"
            )


def _read_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise SweepError(f"{path}: not valid YAML ({err})") from err


def _as_frame(value: Any, where: Path, name: str) -> int:
    try:
        number = float(np.asarray(value).item()) if not isinstance(value, str) else float(value)
    except (TypeError, ValueError) as err:
        raise SweepError(f"{where}: '{name}' is not a frame number: {value!r}") from err
    if not number.is_integer():
        raise SweepError(f"{where}: '{name}' is not a whole frame number: {value!r}")
    return int(number)


def _job_order(run_dir: Path) -> tuple[int, str]:
    name = run_dir.name
    return (int(name), name) if name.isdigit() else (1 << 62, name)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)
