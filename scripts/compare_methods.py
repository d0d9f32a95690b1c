"""Methods side by side on the frames of a capture: held-out and training PSNR per frame, the
all-black floor, and (``--loo``) the leave-one-view-out mean over every camera.

    python scripts/compare_methods.py --frames 5,25,45,65 [--loo] [--out FILE.json] \
        --method default= \
        --method previous="calibration.refine=none debias.method=none grid.resolution=96 solver.tv=0.03" \
        --method nnls="solver=fista solver.l1=0 solver.max_iters=100 calibration.refine=none debias.method=none" \
        --method mart="solver=mart select.auto=false debias.method=none" \
        [scene=scalarflow by default, train.py overrides shared by every method ...]

Each ``--method NAME=OVERRIDES`` is a train.py run with those overrides on top of the shared
ones (an empty one is the scene's default); every frame is loaded once (once per scene node
when a method changes ``scene.*``, e.g. ``scene.downscale=2``) and reconstructed by each
method through the Python API, as ``python train.py`` would. Report on frames that chose
none of the settings compared (say which did). Prints one row per frame and method (held-out
PSNR, SSIM and detail correlation full frame and inside the captured silhouettes, training PSNR
and detail, the black floor), then the means over frames; ``--out`` writes every figure as JSON;
``--figure FOLDER`` draws each frame's held-out views: the capture and every method's render
side by side, titled with PSNR and detail, and their fine-detail bands below (what the detail
correlation compares: a blurred render has a flat grey band).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.evaluate.metrics import detail_band
from flamerecon.evaluate.scores import detail_sigma
from flamerecon.fit.reconstruct import mean_of
from flamerecon.geometry.cameras import camera_subset
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.outputs.figures import detail_comparison, write_png
from flamerecon.outputs.names import file_stem
from flamerecon.run.cli import (
    compose_train,
    frame_list,
    output_file,
    output_folder,
    run_script,
    script_parser,
)
from flamerecon.run.leave_one_out import leave_one_out
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene


def method(text: str) -> tuple[str, list[str]]:
    """'name=k=v k2=v2' -> ('name', ['k=v', 'k2=v2'])."""
    name, sep, overrides = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=OVERRIDES, got '{text}'")
    return name, overrides.split()


def write_figures(folder: Path, frame: int, scene, renders: dict) -> None:
    """heldout-FRAME-VIEW.png per held-out view of ``scene``: the capture, then each method's
    render titled with its PSNR and detail (``renders``: name -> ({view: render (C, H, W)}, its
    held-out scores)), the fine-detail bands below (:func:`detail_comparison`)."""
    sigma = detail_sigma(scene)
    for view in next(iter(renders.values()))[0]:
        images = [scene.images[scene.views.index(view)], *(r[view].cpu() for r, _ in renders.values())]
        titles = [f"captured {view}, frame {frame}",
                  *(f"{name}: {held[view]['psnr']:.2f} dB, detail {held[view]['detail']:.3f}"
                    for name, (_, held) in renders.items())]
        bands = [detail_band(img.float(), sigma).mean(0) for img in images]
        rows, cols = crop_box(images, CROP_MARGIN_PX)
        figure = detail_comparison([img[:, rows, cols] for img in images], [b[rows, cols] for b in bands], titles)
        write_png(folder / f"heldout-{frame}-{file_stem(view)}.png", figure)


#: pixels kept around what the figure shows
CROP_MARGIN_PX = 24


def crop_box(images: list, margin: int) -> tuple[slice, slice]:
    """The rows and columns of images (C, H, W) where any of them exceeds 5% of its peak,
    grown by ``margin`` pixels (the whole frame when every image is black): the figure shows
    the plume and its ghosts, not the empty frame around them."""
    H, W = images[0].shape[-2:]
    lit = sum((img.float().mean(0) > 0.05 * float(img.max())) for img in images if float(img.max()) > 0)
    if not torch.is_tensor(lit) or not bool(lit.any()):
        return slice(0, H), slice(0, W)
    ys, xs = lit.nonzero(as_tuple=True)
    return (slice(max(0, int(ys.min()) - margin), min(H, int(ys.max()) + margin + 1)),
            slice(max(0, int(xs.min()) - margin), min(W, int(xs.max()) + margin + 1)))


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides shared by every method")
    parser.add_argument("--frames", type=frame_list, required=True, help="comma-separated scene.frame values")
    parser.add_argument("--method", type=method, action="append", required=True, metavar="NAME=OVERRIDES")
    parser.add_argument("--loo", action="store_true", help="also the leave-one-view-out mean over every camera "
                        "(strict protocol: each held-out camera as the calibration file gives it)")
    parser.add_argument("--rig", action="store_true", help="with --loo, also the rig-calibrated leave-one-view-out "
                        "(calibration.rig=true: every camera refined on calibration.frames, never scored)")
    parser.add_argument("--figure", type=output_folder, metavar="FOLDER",
                        help="write FOLDER/heldout-FRAME-VIEW.png per frame and held-out view: the capture and "
                        "each method's render (PSNR and detail in the titles), their fine-detail bands below")
    parser.add_argument("--out", type=output_file, help="JSON file of every figure (with --loo, the folds' run "
                        "folders go into the folder of its name without suffix; default outputs/compare)")
    args = parser.parse_args(argv)
    folds = parser.checked("--out", output_folder, str(Path(args.out or "outputs/compare").with_suffix(""))) \
        if args.loo else None

    columns = [  # (key, heading, format) of each figure of a row
        ("heldout", "held-out dB", "12.2f"), ("ssim", "SSIM", "7.4f"), ("detail", "detail", "7.3f"),
        ("detail_sil", "det sil", "7.3f"), ("train", "train dB", "9.2f"), ("train_detail", "tr det", "7.3f"),
        ("black", "black dB", "9.2f"),
        *([("loo", "LOO mean dB", "12.2f"), ("loo_detail", "LOO det", "8.3f")] if args.loo else []),
        *([("rig", "rig LOO dB", "11.2f"), ("rig_detail", "rig det", "8.3f")] if args.loo and args.rig else []),
        ("seconds", "seconds", "8.1f")]

    def line(frame: str, name: str, row: dict) -> str:
        return f"{frame:>5} {name:<12} " + " ".join(format(row[k], f) for k, _, f in columns)

    def run() -> None:
        rows = []
        print(f"{'frame':>5} {'method':<12} " + " ".join(f"{h:>{f.split('.')[0]}}" for _, h, f in columns),
              flush=True)
        for frame in args.frames:
            scenes, renders = {}, {}  # scenes loaded once per frame and scene node: a method may change scene.*
            for name, extra in args.method:
                cfg = compose_train([*args.overrides, *extra, f"scene.frame={frame}"])
                key = OmegaConf.to_yaml(cfg.scene)
                scene = scenes[key] = scenes[key] if key in scenes else load_scene(cfg.scene)
                clock = time.perf_counter()
                result = fr.reconstruct(scene, options_from_config(cfg))
                metrics = fr.score(result)
                held = metrics["heldout"]
                if args.figure:
                    views = [scene.views[v] for v in result.setup.holdout]
                    renders[name] = (dict(zip(views, fr.render(result.density, result.grid, camera_subset(
                        result.scene.cameras, result.setup.holdout), result.setup.step))), held)
                row = {"frame": frame, "method": name, "overrides": extra,
                       "heldout": mean_of(held, "psnr"), "ssim": mean_of(held, "ssim"),
                       "detail": mean_of(held, "detail"), "detail_sil": mean_of(held, "detail_silhouette"),
                       "train": mean_of(metrics["train"], "psnr"), "train_detail": mean_of(metrics["train"], "detail"),
                       "black": mean_of(held, "psnr_black"), "seconds": time.perf_counter() - clock}
                if args.loo:
                    loo = leave_one_out(cfg, folds / f"{frame}-{name}",
                                        scene=scene)
                    row["loo"], row["loo_detail"] = loo["mean"]["psnr"], loo["mean"]["detail"]
                    row["loo_views"] = {v: r["psnr"] for v, r in loo["views"].items()}
                if args.loo and args.rig:
                    rig_cfg = compose_train([*args.overrides, *extra, f"scene.frame={frame}", "calibration.rig=true"])
                    rig = leave_one_out(rig_cfg, folds / f"{frame}-{name}-rig", scene=scene)
                    row["rig"], row["rig_detail"] = rig["mean"]["psnr"], rig["mean"]["detail"]
                    row["rig_views"] = {v: r["psnr"] for v, r in rig["views"].items()}
                rows.append(row)
                print(line(str(frame), name, row), flush=True)
                if args.out:
                    write_json_atomic(args.out, {"shared": args.overrides, "rows": rows})
            if args.figure:
                write_figures(args.figure, frame, next(iter(scenes.values())), renders)
        for name, _ in args.method:
            mine = [r for r in rows if r["method"] == name]
            print(line("mean", name, {k: sum(r[k] for r in mine) / len(mine) for k, _, _ in columns}))

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
