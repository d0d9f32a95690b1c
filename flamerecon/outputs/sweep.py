"""A multirun's jobs side by side: one row per job folder (``0/``, ``1/``, ...) with what set it
apart (the overrides that differ between the jobs) and its scores from metrics.json, printed at
the end of ``python train.py -m ...`` and by ``scripts/assemble.py``, and kept as
``sweep_summary.csv`` in the sweep folder."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import yaml

from flamerecon.outputs.atomic import atomic_write_text

SUMMARY_CSV = "sweep_summary.csv"
#: the marker of a failed run or job (run/runner.py writes it; a sweep's table reads it)
FAILED_FILE = "FAILED"
#: the columns after the overrides: (name, metrics.json's value, format)
COLUMNS = (("heldout PSNR dB", ("heldout", "psnr"), "{:.2f}"), ("black dB", ("heldout", "psnr_black"), "{:.2f}"),
           ("SSIM", ("heldout", "ssim"), "{:.4f}"), ("detail", ("heldout", "detail"), "{:.3f}"),
           ("train PSNR dB", ("train", "psnr"), "{:.2f}"), ("iterations", ("solver", "iterations"), "{:d}"),
           ("seconds", ("solver", "seconds"), "{:.1f}"))
#: the column a sweep's table gains where a job ran ``leave_one_out=true`` (every camera fitted: no
#: held-out score; each camera left out in turn instead)
LOO_COLUMN = ("leave-one-out PSNR dB", ("leave_one_out", "psnr"), "{:.2f}")


def _job_folders(sweep_dir: Path) -> list[Path]:
    jobs = [d for d in sweep_dir.iterdir() if d.is_dir() and (d / ".hydra").is_dir()]
    return sorted(jobs, key=lambda d: (int(d.name), d.name) if d.name.isdigit() else (1 << 62, d.name))


def _overrides(job: Path) -> dict[str, str]:
    path = job / ".hydra" / "overrides.yaml"
    try:
        items = yaml.safe_load(path.read_text()) if path.is_file() else []
    except yaml.YAMLError:
        items = []
    return dict(str(o).split("=", 1) for o in items or [] if "=" in str(o))


def _value(metrics: dict, where: tuple[str, str]):
    """A score: the mean over the views of ``heldout``/``train``, or the ``solver``'s own."""
    section, key = where
    node = metrics.get(section) if isinstance(metrics, dict) else None
    if not isinstance(node, dict):
        return None
    if section == "solver":
        return node.get(key) if isinstance(node.get(key), (int, float)) else None
    if section == "leave_one_out":
        node = node.get("views") if isinstance(node.get("views"), dict) else {}
    values = [v[key] for v in node.values() if isinstance(v, dict) and isinstance(v.get(key), (int, float))]
    return sum(values) / len(values) if values else None


def sweep_rows(sweep_dir: str | os.PathLike) -> tuple[list[str], list[dict[str, str]]]:
    """(the overrides that differ between the jobs, one row per job: ``job``, those overrides,
    the :data:`COLUMNS` formatted, ``status`` finished | FAILED: <why> | unfinished)."""
    jobs = _job_folders(Path(sweep_dir))
    overrides = [_overrides(job) for job in jobs]
    keys = sorted({k for o in overrides for k in o})
    varying = [k for k in keys if len({o.get(k) for o in overrides}) > 1]
    rows, found = [], []
    for job in jobs:
        path = job / "metrics.json"
        try:
            found.append(json.loads(path.read_text()) if path.is_file() else {})
        except json.JSONDecodeError:
            found.append({})
    columns = sweep_columns(found)
    for job, given, metrics in zip(jobs, overrides, found):
        row = {"job": job.name, **{k: given.get(k, "") for k in varying}}
        for name, where, fmt in columns:
            value = _value(metrics, where)
            row[name] = "" if value is None else fmt.format(int(value) if fmt == "{:d}" else float(value))
        failed = job / FAILED_FILE
        row["status"] = (f"FAILED: {(failed.read_text().splitlines() or [''])[0]}" if failed.is_file()
                         else "finished" if metrics else "unfinished")
        rows.append(row)
    return varying, rows


def sweep_columns(metrics: list[dict]) -> tuple:
    """The table's score columns for jobs with these metrics: :data:`COLUMNS`, and
    :data:`LOO_COLUMN` where a job has a leave-one-out record."""
    return COLUMNS + ((LOO_COLUMN,) if any(isinstance(m, dict) and m.get("leave_one_out") for m in metrics) else ())


def sweep_table(sweep_dir: str | os.PathLike) -> str:
    """The jobs of a multirun as a plain-text table (held-out scores are means over the
    held-out views), headed by the sweep folder."""
    varying, rows = sweep_rows(sweep_dir)
    if not rows:
        return f"{sweep_dir}: no job folders"
    names = ["job", *varying, *(k for k in rows[0] if k not in ("job", "status", *varying)), "status"]
    widths = [max(len(n), *(len(r[n]) for r in rows)) for n in names]
    lines = [f"{sweep_dir}: {len(rows)} jobs" + (f", differing in {', '.join(varying)}" if varying else ""),
             "  ".join(n.rjust(w) for n, w in zip(names, widths))]
    lines += ["  ".join(r[n].rjust(w) for n, w in zip(names, widths)) for r in rows]
    return "\n".join(lines)


def write_sweep_csv(sweep_dir: str | os.PathLike) -> Path:
    """``sweep_summary.csv`` in the sweep folder: :func:`sweep_rows`, one line per job."""
    varying, rows = sweep_rows(sweep_dir)
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=["job", *varying, *(c[0] for c in COLUMNS), "status"])
    writer.writeheader()
    writer.writerows(rows)
    path = Path(sweep_dir) / SUMMARY_CSV
    atomic_write_text(path, out.getvalue())
    return path
