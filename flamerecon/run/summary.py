"""What a finished run prints and logs: the summary table, its time split, the flat metrics
TensorBoard's hparams and multirun sweeps read."""

from __future__ import annotations

import math

from flamerecon.fit.reconstruct import mean_of
from flamerecon.fit.refine_cameras import found_nothing


def summary_table(metrics: dict) -> str:
    """The short table printed at the end of a run."""
    s = metrics["solver"]
    held = list(metrics["heldout"].values())
    rows = [
        ("held-out PSNR [dB]", psnr_text(metrics["heldout"], "psnr", "psnr_black")),
        ("held-out SSIM", f"{mean_of(metrics['heldout'], 'ssim'):.4f}"),
    ] if held else [("held-out views", f"none: all {len(metrics['train'])} cameras fitted, so no camera measured "
                                       + ("this result; the leave-one-view-out below scores each left out in turn"
                                          if metrics.get("leave_one_out") else
                                          "this result; leave_one_out=true (or scripts/leave_one_out.py with the "
                                          "same overrides) scores each camera left out in turn"))]
    aligned = {name: v for name, v in metrics["heldout"].items() if math.isfinite(v.get("psnr_aligned", math.nan))}
    if aligned:  # undefined where a half of the view is dark: printed only where it means something
        rows.append(("  appearance-aligned [dB]", psnr_text(aligned, "psnr_aligned", None,
                                                            "gain fitted on the left half, PSNR of the right half")))
    if held and "psnr_predicted" in held[0]:
        u = metrics.get("uncertainty", {})
        note = (f"by the confidence: {len(u.get('members', []))} members + shifts of "
                f"{u.get('shift_voxels', 0):g} voxel, {u.get('seconds', 0.0):.1f} s, and the training images' "
                "sensor noise; uncertainty.npz")
        rows.append(("  predicted [dB]", f"{mean_of(metrics['heldout'], 'psnr_predicted'):.2f}  ({note})"))
    if held and "psnr_silhouette" in held[0]:
        rows.append(("  inside silhouettes [dB]", psnr_text(metrics["heldout"], "psnr_silhouette",
                                                            "psnr_black_silhouette")))
    if held and "detail" in held[0]:
        inside = (f", inside the captured silhouettes {mean_of(metrics['heldout'], 'detail_silhouette'):.3f}"
                  if "detail_silhouette" in held[0] else "")
        rows.append(("held-out detail", (f"{mean_of(metrics['heldout'], 'detail'):.3f}{inside}  "
                                         "(fine-structure correlation, 1 = all of it)")))
    if held and "psnr_native" in held[0]:
        W, H = metrics["resolution"]["native"]
        rows += [
            (f"  native {W}x{H} PSNR [dB]", psnr_text(metrics["heldout"], "psnr_native", "psnr_black_native")),
            (f"  native {W}x{H} SSIM", f"{mean_of(metrics['heldout'], 'ssim_native'):.4f}"),
        ]
    loo = metrics.get("leave_one_out")
    if loo:
        m = loo["mean"]
        rows.append(("leave-one-view-out [dB]", f"{m['psnr']:.2f}  (black image: {m['psnr_black']:.2f}; detail "
                     f"{m['detail']:.3f}; {loo['protocol']}; "
                     + ", ".join(f"{name} {r['psnr']:.2f}" for name, r in loo["views"].items()) + ")"))
    rows.append(("training PSNR [dB]", f"{mean_of(metrics['train'], 'psnr'):.2f}"
                 + (f"  (detail {mean_of(metrics['train'], 'detail'):.3f})" if "detail" in (
                     next(iter(metrics["train"].values()), {})) else "")))
    c = metrics.get("calibration")
    if c:
        fitted = f", fitted to frames {c['frames']}" if c.get("frames") else ""
        held = (f"; held-out {c['heldout_psnr_before']:.2f} dB with the capture's cameras in the camera fit's "
                "first solve" if math.isfinite(c.get("heldout_psnr_before", math.nan)) else "")
        rows.append((f"calibration ({c['refine']}{fitted})", (
            f"training {c['train_psnr_before']:.2f} -> {c['train_psnr_after']:.2f} dB{held} "
            "(calibration.refine=none runs the whole pipeline)") if "train_psnr_before" in c else (
            f"training {c['train_psnr_after']:.2f} dB (calibration.score_before=true: also with the "
            "capture's own cameras, one more solve)")))
        rows.append(("  cameras", calibration_source(c)))
        if c.get("limiting_camera"):
            rows.append(("  calibration limits", limiting_text(c, metrics.get("uncertainty", {}).get("poses", {}))))
        elif c.get("frames"):  # a capture calibration kept without the pose offsets (calibration.offsets)
            rows.append(("  calibration limits", ("not measured: calibration.offsets=true (or uncertainty.enabled=true) "
                                                  "measures each camera's pose error, once per capture (a calibration.file holds its own or none)")))
        if found_nothing(c.get("rounds") or []):
            rows.append(("  found", (f"nothing to correct: {c['rounds'][0]['stopped']}; the capture's cameras "
                                     "are kept (calibration.refine=none skips the fit)")))
        else:
            rows += [(f"  {name}", (f"{r['rotation_deg']:.3f} deg, {r['translation']:.4g} world units, "
                                    f"focal x{r['focal_scale']:.4f}, principal point "
                                    f"({r['principal_point_px'][0]:+.2f}, {r['principal_point_px'][1]:+.2f}) px, "
                                    f"box moves {r['box_px']:.2f} px"))
                     for name, r in c["cameras"].items()]
    if "scene" in metrics:
        rows.append(("scene axes", scene_axes(metrics["scene"])))
    if "volume" in metrics:
        rows.append(("volume rel. L2 / IoU", f"{metrics['volume']['rel_l2']:.4f} / {metrics['volume']['iou']:.4f}"))
    rows += [
        ("solver", f"{s['name']} (l1 = {s['l1']:.4g})"),
        ("iterations", f"{s['iterations']}" + (
            "" if s.get("converged", True) else " (stopped by the budget"
            + (f"; relative duality gap {s['rel_gap']:.1e})" if "rel_gap" in s else ")"))),
        ("seconds", f"{s['seconds']:.2f}"),
    ]
    if "timing" in metrics:
        rows.append(("time split [s]", time_split(metrics["timing"])))
    if "memory" in metrics:
        rows.append(("peak memory [GiB]", f"{metrics['memory']['resident']:.2f} resident" + (
            f", {metrics['memory']['device']:.2f} on the GPU" if "device" in metrics["memory"] else "")))
    if "levels" in s:
        rows.append(("grid levels", "; ".join(
            f"{cells_of(r['resolution'])}" + (f" on {r['image'][0]}x{r['image'][1]} px" if "image" in r else "")
            + f": {r['iterations']} it, {r['setup_seconds']:.2f} s setup + {r['seconds']:.2f} s solve"
            for r in s["levels"])))
    width = max(len(r[0]) for r in rows)
    return "\n".join([f"  {k:<{width}}  {v}" for k, v in rows] + warnings_block(metrics.get("warnings", [])))


def limiting_text(c: dict, poses: dict) -> str:
    """The camera whose pose error cost its images most (metrics.json's
    ``calibration.limiting_camera``), with its pose uncertainty when the confidence has it."""
    name = c["limiting_camera"]
    text = (f"{name}: its pose error cost its images {c['limiting_lost_db']:.2f} dB on the calibration frames, the "
            "most of any camera")
    if name in poses:
        r = poses[name]
        text += (f"; uncertain by {r['pose_sigma_deg']:.2f} deg, {r['pose_sigma_box_px']:.2f} px at the box "
                 "(every camera's in metrics.json uncertainty.poses)")
    return text


def psnr_text(per_view: dict, key: str, black: str | None, note: str = "") -> str:
    """A PSNR's mean over the views where it is defined, with the all-black floor's (``black``)
    and ``note``; ``undefined (held-out view is black)`` when no view has one."""
    defined = {name: v for name, v in per_view.items() if "psnr_undefined" not in v}
    if per_view and not defined:
        return "undefined (held-out view is black)"
    notes = [f"black image: {mean_of(defined, black):.2f}"] if black else []
    notes += [note] if note else []
    if len(defined) < len(per_view):
        notes.append(f"{len(per_view) - len(defined)} black held-out view(s) left out: undefined")
    return f"{mean_of(defined, key):.2f}" + (f"  ({'; '.join(notes)})" if notes else "")


def warnings_block(warnings: list[dict]) -> list[str]:
    """The summary's last lines: metrics.json's ``warnings``, one per line (none: no lines)."""
    if not warnings:
        return []
    return [f"  WARNINGS ({len(warnings)}): the scores above may mean little"] + [
        f"  ! {w['code']}: {w['message']}" for w in warnings]


def scene_axes(record: dict) -> str:
    """metrics.json's ``scene`` record as the summary says it: up axis (and why), unit, frame rate."""
    unit = "world units of unknown length (scene.unit sets metres per unit)" if record["unit"] is None else (
        f"1 world unit = {record['unit']:g} m")
    rate = "frame rate unknown" if record["frame_rate"] is None else f"{record['frame_rate']:g} frames/s"
    return f"up {record['up']} ({record['up_source']}); {unit}; {rate}"


def calibration_source(record: dict) -> str:
    """Where a run's refined cameras came from, from metrics.json's ``calibration`` record."""
    if record.get("source") == "read":
        return f"read from {record['file']}"
    return "fitted now" + (f", kept in {record['file']}" if record.get("file") else " (this frame's, in cameras.json)")


def cells_of(resolution) -> str:
    """``nx x ny x nz`` of a resolution (nx, ny, nz), for messages."""
    return "x".join(str(n) for n in resolution)


def time_split(timing: dict[str, float]) -> str:
    """metrics.json's ``timing`` as one line, e.g. ``scene 0.4, setup 1.2 (assembly 0.8), ...``."""
    parts = [f"{k.replace('_', ' ')} {v:.2f}" + (f" (assembly {timing['assembly']:.2f})" if k == "setup" else "")
             for k, v in timing.items() if k != "assembly"]
    return ", ".join(parts)


def flat_metrics(metrics: dict) -> dict[str, float]:
    """The headline numbers of metrics.json, flat (TensorBoard hparams, sweep summaries)."""
    out = {
        "heldout_psnr": mean_of(metrics["heldout"], "psnr"),
        "heldout_ssim": mean_of(metrics["heldout"], "ssim"),
        "heldout_detail": mean_of(metrics["heldout"], "detail"),
        "train_psnr": mean_of(metrics["train"], "psnr"),
        "seconds": metrics["solver"]["seconds"],
    }
    if "volume" in metrics:
        out.update({f"volume_{k}": v for k, v in metrics["volume"].items()})
    return out
