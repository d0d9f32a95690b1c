"""The opencv and nerf scenes' defaults against NNLS on a synthetic stand-in for a real flame
capture (``scene=synthetic_flame``: a smooth flame, 7 unevenly spaced cameras, sensor noise, every
camera given to the solver off by a few pixels), over several flame instances (seeds).

    python scripts/flame_benchmark.py --seeds 2,3,4 [--folds 1] [--out FILE.json] \
        [--method NAME=OVERRIDES ...] [train.py overrides shared by every method ...]

Methods (without ``--method``), each a train.py run on top of the shared overrides:

- ``nnls``: the opencv scene's defaults (hull rays, gain debias, pose refinement) with
  ``solver=fista solver.l1=0 select.auto=false`` (with l1 given, every fista candidate of the
  selection is the same NNLS, so selecting changes nothing but the time);
- ``opencv``: the defaults ``scene=opencv`` runs with (read from conf/scene/opencv.yaml);
- ``nerf``: those of ``scene=nerf`` (conf/scene/nerf.yaml);
- ``tv_fixed``: the opencv defaults with ``select.auto=false`` (conf/solver/tv.yaml's weights).

Seed s holds out ``--folds`` views in turn (view s mod n first, then evenly spread), each fitted
from all the others, scored as the calibration gives the held-out camera (its error too). Prints
one row per seed and method (held-out PSNR, SSIM and detail correlation, training PSNR, the
weights the run chose, seconds), then per method the means over seeds and the paired gain over
the first method. Report on seeds that chose none of the settings compared (say which did).
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first, before the slow imports: a stop signal ends in one line, exit status 130

import argparse
import sys
import time

from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.evaluate.scores import render_scene_views, score_rendered
from flamerecon.fit.reconstruct import mean_of
from flamerecon.outputs.atomic import write_json_atomic
from flamerecon.resources import config_dir
from flamerecon.run.cli import (
    at_least,
    compose_train,
    frame_list,
    output_file,
    run_script,
    script_parser,
)
from flamerecon.run.pipeline import options_from_config
from flamerecon.scenes import load_scene


def method(text: str) -> tuple[str, list[str]]:
    """'name=k=v k2=v2' -> ('name', ['k=v', 'k2=v2'])."""
    name, sep, overrides = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=OVERRIDES, got '{text}'")
    return name, overrides.split()


def preset_overrides(scene: str) -> list[str]:
    """The run settings of ``conf/scene/<scene>.yaml`` (its solver group and every node but
    ``scene:``) as train.py overrides, so that another scene runs with them."""
    node = OmegaConf.to_container(OmegaConf.load(config_dir() / "scene" / f"{scene}.yaml"))
    found = []
    for entry in node.pop("defaults", []):
        for key, value in (entry.items() if isinstance(entry, dict) else ()):
            found.append(f"{key.removeprefix('override /')}={value}")
    node.pop("scene", None)

    def leaves(prefix: str, value) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                leaves(f"{prefix}.{k}" if prefix else k, v)
        else:
            found.append(f"{prefix}={'null' if value is None else str(value).lower() if isinstance(value, bool) else value}")

    leaves("", node)
    return found


def seed_list(text: str) -> list[int]:
    """argparse type: '2,3,4' -> [2, 3, 4] (seeds >= 0, at least one)."""
    try:
        return frame_list(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected comma-separated seeds >= 0, got '{text}'") from None


def merged(*overrides: str) -> list[str]:
    """Overrides with the last of each key only (Hydra refuses a group chosen twice)."""
    last = {o.partition("=")[0]: o for o in overrides}
    return list(last.values())


def default_methods() -> list[tuple[str, list[str]]]:
    opencv = preset_overrides("opencv")
    return [("nnls", merged(*opencv, "solver=fista", "solver.l1=0", "select.auto=false")),
            ("opencv", opencv), ("nerf", preset_overrides("nerf")), ("tv_fixed", merged(*opencv, "select.auto=false"))]


def held_views(views: list[str], seed: int, folds: int) -> list[str]:
    """The views seed ``seed`` holds out in turn: view seed mod n, then evenly spread."""
    n = len(views)
    return [views[(seed + (j * n) // folds) % n] for j in range(min(folds, n))]


def true_camera_psnr(rec, true_scene, view: str) -> float:
    """Held-out PSNR of the run's density through the camera that rendered ``view``'s image
    (what the held-out camera's own calibration error costs); NaN without such a scene."""
    if true_scene is None:
        return float("nan")
    v = true_scene.views.index(view)
    image = render_scene_views(rec.setup.volume(rec.fit.result.x), rec.setup.grid, true_scene, [v], rec.setup.step)
    return score_rendered(image, true_scene, [v])[view]["psnr"]


def chosen(rec) -> str:
    """The weights the run solved with: the selection's choice, else the solver's own."""
    if rec.fit.selection is not None:
        return " ".join(f"{k}={v:g}" for k, v in rec.fit.selection["chosen"].items())
    s = rec.fit.options.solver
    weights = {"l1": s.l1, "l1_rel": s.l1_rel, "tv": s.params.get("tv")}
    if weights["l1"] is not None:  # an absolute l1 wins over l1_rel
        weights.pop("l1_rel")
    return " ".join(f"{k}={v:g}" for k, v in weights.items() if v is not None) or "-"


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("overrides", nargs="*", help="train.py overrides shared by every method "
                        "(scene=synthetic_flame unless one is given)")
    parser.add_argument("--seeds", type=seed_list, default=[2, 3, 4], help="comma-separated scene.seed values")
    parser.add_argument("--folds", type=at_least(1), default=1, help="views held out in turn per seed")
    parser.add_argument("--method", type=method, action="append", metavar="NAME=OVERRIDES",
                        help="replaces the default methods (repeat it)")
    parser.add_argument("--out", type=output_file, help="JSON file of every figure")
    args = parser.parse_args(argv)
    methods = args.method or default_methods()
    columns = [("heldout", "held-out dB", "12.2f"), ("ssim", "SSIM", "7.4f"), ("detail", "detail", "7.3f"),
               ("true_cam", "true cam dB", "12.2f"), ("train", "train dB", "9.2f"), ("seconds", "seconds", "8.1f")]

    def line(seed: str, name: str, row: dict, extra: str = "") -> str:
        return f"{seed:>5} {name:<10} " + " ".join(format(row[k], f) for k, _, f in columns) + f"  {extra}"

    def run() -> None:
        rows = []
        print(f"{'seed':>5} {'method':<10} " + " ".join(f"{h:>{f.split('.')[0]}}" for _, h, f in columns)
              + "  chosen weights (per held-out view)", flush=True)
        for seed in args.seeds:
            scene = None
            for name, extra in methods:
                cfg = compose_train(merged(*args.overrides, *extra, f"scene.seed={seed}"), "synthetic_flame")
                if scene is None:
                    scene = load_scene(cfg.scene)
                    error = float(cfg.scene.get("calibration_error", 0.0) or 0.0)
                    true_scene = load_scene({**OmegaConf.to_container(cfg.scene, resolve=True),
                                             "calibration_error": 0.0}) if error > 0 else None
                options = options_from_config(cfg)
                folds = []
                for view in held_views(scene.views, seed, args.folds):
                    clock = time.perf_counter()
                    rec = fr.reconstruct(scene, options.replace(holdout=(view,)))
                    metrics = fr.score(rec)
                    held = metrics["heldout"]
                    folds.append({"view": view, "heldout": mean_of(held, "psnr"), "ssim": mean_of(held, "ssim"),
                                  "detail": mean_of(held, "detail"), "train": mean_of(metrics["train"], "psnr"),
                                  "true_cam": true_camera_psnr(rec, true_scene, view),
                                  "chosen": chosen(rec), "seconds": time.perf_counter() - clock,
                                  "selection": rec.fit.selection})
                row = {k: sum(f[k] for f in folds) / len(folds) for k, _, _ in columns}
                row.update(seed=seed, method=name, overrides=extra, folds=folds)
                rows.append(row)
                print(line(str(seed), name, row, "; ".join(f"{f['view']}: {f['chosen']}" for f in folds)), flush=True)
                if args.out:
                    write_json_atomic(args.out, {"shared": args.overrides, "rows": rows})
        first = methods[0][0]
        for name, _ in methods:
            mine = [r for r in rows if r["method"] == name]
            base = {r["seed"]: r["heldout"] for r in rows if r["method"] == first}
            gains = [r["heldout"] - base[r["seed"]] for r in mine]
            print(line("mean", name, {k: sum(r[k] for r in mine) / len(mine) for k, _, _ in columns},
                       f"{sum(gains) / len(gains):+.2f} dB over {first} (min {min(gains):+.2f})"))

    return run_script(run, args.debug)


if __name__ == "__main__":
    sys.exit(main())
