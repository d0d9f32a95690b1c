"""Leave-one-view-out: reconstruct K times, each time holding out one camera and fitting the
others, and score every held-out view (the scene is loaded once; each split is prepared anew).

``exclude`` drops views from every fit without scoring them, so that settings can be chosen
by cross-validation over the training views without ever looking at a test view. (``init=``
warm-starts every fold from the same finished run, which may have seen the held-out view: leave
it unset when the numbers are to be honest held-out scores.) ``grid.levels`` are solved anew in
every fold, on that fold's training views only.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from flamerecon import interrupt
from flamerecon.device import resolve_device
from flamerecon.evaluate.scores import render_scene_views, score_rendered, write_renders
from flamerecon.fit.build import build
from flamerecon.fit.option_rules import check_options
from flamerecon.fit.reconstruct import calibrated_scene, fit, warm_start
from flamerecon.fit.refine_cameras import found_nothing
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.progress import Progress
from flamerecon.run.config import options_from_config
from flamerecon.scenes import Scene, SceneError, load_scene

log = logging.getLogger(__name__)

#: the per-view numbers averaged into the table's last row.
AVERAGED = ("psnr", "ssim", "detail", "detail_silhouette", "psnr_black", "psnr_silhouette",
            "psnr_black_silhouette")


def leave_one_out(cfg: DictConfig, out_dir: str | Path, views: list[str] | None = None,
                  exclude: list[str] | None = None, progress=None, scene: Scene | None = None) -> dict:
    """Hold out each of ``views`` in turn (default: every view not in ``exclude``), fit the
    rest (minus ``exclude``) as ``cfg`` says, score the held-out view. Writes
    ``out_dir/loo.json`` and ``out_dir/renders/<view>.png``; returns loo.json's dict:
    ``views`` {name: scores, iterations, seconds, l1, train}, ``mean`` over views of
    :data:`AVERAGED`, ``exclude``, ``config``. ``progress(name, row)`` is called per view.
    ``scene`` is ``cfg.scene`` already loaded (loaded here when None)."""
    check_options(OmegaConf.to_container(cfg, resolve=True))
    out_dir = Path(out_dir)
    device = resolve_device(cfg.device)
    scene = load_scene(cfg.scene) if scene is None else scene
    exclude = list(exclude or [])
    for name in [*exclude, *(views or [])]:
        if name not in scene.views:
            raise SceneError(f"leave-one-out: unknown view '{name}'; scene '{scene.name}' has {scene.views}")
    views = list(views) if views else [v for v in scene.views if v not in exclude]
    if len(scene.views) - len(exclude) < 2:
        raise SceneError(f"leave-one-out: excluding {exclude} leaves fewer than two views of {scene.views}")
    options, kept = once_for_the_capture(options_from_config(cfg), scene, exclude, device)
    silhouette = options.silhouette.as_dict()
    rows = {}
    folds = Progress("leave-one-out", len(views), unit="fold")
    for name in views:
        interrupt.check()
        split = options.replace(holdout=(name, *[e for e in exclude if e != name]))
        fold, _ = calibrated_scene(scene, split, device)  # calibration.refine: this fold's cameras
        setup = build(fold, split, device)
        x0 = warm_start(fold, split, device, setup)  # init= and/or grid.levels
        found = fit(setup, split, x0)
        result, l1 = found.result, found.l1
        v = scene.views.index(name)
        image = render_scene_views(setup.volume(result.x), setup.grid, scene, [v], setup.step)
        row = score_rendered(image, scene, [v], silhouette)[name]
        row.update(iterations=result.iterations, seconds=result.seconds, l1=l1,
                   train=[scene.views[i] for i in setup.train])
        rows[name] = row
        write_renders(out_dir, image, scene, [v])
        folds.step(f"{name} held out")
        if progress is not None:
            progress(name, row)
    mean = {k: sum(r[k] for r in rows.values()) / len(rows) for k in AVERAGED}
    record = {"views": rows, "mean": mean, "exclude": exclude, "protocol": protocol(options),
              "config": OmegaConf.to_container(cfg, resolve=False)}
    if kept:
        record["calibration"] = kept
    write_json_atomic(out_dir / "loo.json", record)
    return record


def once_for_the_capture(options, scene: Scene, exclude: list[str], device) -> tuple[object, str | None]:
    """The options every fold runs with, and why the camera fit was left out of them (None
    where it was not). The strict protocol fits each fold's training cameras without its
    held-out one: a fit per fold. The fit of every camera (but ``exclude``) runs first, once
    for the capture (or is read from its calibration file); where it found nothing to correct
    (:func:`~flamerecon.fit.refine_cameras.found_nothing`) a fold's fit, on fewer cameras, has
    nothing to find either, and every fold keeps the capture's cameras."""
    c = options.calibration
    if c.refine == "none" or c.file or c.rig:
        return options, None
    _, record = calibrated_scene(scene, options.replace(holdout=tuple(exclude)), device)
    if not found_nothing(record["rounds"]):
        return options, None
    why = (f"the camera fit of all {len(scene.views) - len(exclude)} cameras found nothing to correct "
           f"({record['rounds'][0]['stopped']}): every fold keeps the capture's cameras")
    log.info("leave-one-out: %s", why)
    return options.replace(calibration=replace(c, refine="none")), why


def protocol(options) -> str:
    """How a held-out camera is calibrated: ``strict`` (as the calibration file gives it) or
    ``rig-calibrated`` (refined with the rig on frames that are not scored, ``calibration.rig``)."""
    c = options.calibration
    return "rig-calibrated" if c.refine != "none" and c.rig else "strict"


def loo_table(record: dict) -> str:
    """The table printed at the end: one row per held-out view and the mean."""
    head = (f"  {'view':<12} {'PSNR':>7} {'SSIM':>7} {'detail':>7} {'det sil':>7} {'black':>7} "
            f"{'PSNR sil':>9} {'black sil':>9}")
    lines = [head, "  " + "-" * (len(head) - 2)]

    def line(name: str, r: dict) -> str:
        vals = [r["psnr"], r["ssim"], r["detail"], r["detail_silhouette"], r["psnr_black"],
                r["psnr_silhouette"], r["psnr_black_silhouette"]]
        p, s, d, ds, b, ps, bs = (x if math.isfinite(x) else float("nan") for x in vals)
        return f"  {name:<12} {p:7.2f} {s:7.4f} {d:7.3f} {ds:7.3f} {b:7.2f} {ps:9.2f} {bs:9.2f}"

    lines += [line(name, r) for name, r in record["views"].items()]
    lines += ["  " + "-" * (len(head) - 2), line("mean", record["mean"])]
    if record["exclude"]:
        lines.append(f"  (excluded from every fit: {', '.join(record['exclude'])})")
    lines.append(f"  protocol: {record['protocol']} (each held-out camera "
                 + ("refined with the rig on calibration.frames, none of them scored)" if record["protocol"] != "strict"
                    else "as the calibration file gives it)"))
    if record.get("calibration"):
        lines.append(f"  cameras: {record['calibration']}")
    return "\n".join(lines)
