"""The assembled operator of a frame, measured: its nonzeros against the size estimate that
chooses the backend, the assembly's time, and the process's resident memory sampled every 3 ms
before the assembly, while the rays' chunks are assembled and while A^T is built.

    python scripts/operator_memory.py [--downscale 1 --grid 256] [scene=scalarflow by default, overrides ...]

Peaks are of the whole process (what `top` shows), so the peak above "before" is what the
assembly adds; the finished operator keeps 16 bytes a nonzero (int32 column and float32 value,
in A and in A^T). The camera fit is not run (calibration.refine=none): its cameras move the
silhouettes' rays by a few pixels, not the operator's size.
"""

from __future__ import annotations

from flamerecon.interrupt import install

if __name__ == "__main__":
    install()  # first: a stop signal from here on ends in one line, exit status 130

import os
import threading
import time

from flamerecon.run.cli import at_least, compose_train, run_script, script_parser


def resident_gib() -> float:
    """This process's resident memory now, GiB (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**30
    except (OSError, ValueError, IndexError):
        return 0.0


class Sampler:
    """The largest resident memory seen in each named phase, sampled every 3 ms in a thread."""

    def __init__(self) -> None:
        self.phase, self.peaks, self.running = "before", {}, True
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while self.running:
            self.peaks[self.phase] = max(self.peaks.get(self.phase, 0.0), resident_gib())
            time.sleep(0.003)

    def stop(self) -> dict[str, float]:
        self.running = False
        self.thread.join()
        return self.peaks


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, __file__)
    parser.add_argument("--downscale", type=at_least(1), default=None, help="scene.downscale (default: the preset's)")
    parser.add_argument("--grid", type=at_least(2), default=None, help="grid.resolution (default: the preset's)")
    parser.add_argument("overrides", nargs="*", help="train.py overrides (default: scene=scalarflow)")
    args = parser.parse_args(argv)

    def run() -> None:
        from flamerecon.fit.build import build, fit_pixels
        from flamerecon.geometry.cameras import camera_subset
        from flamerecon.operators import projector, sparse
        from flamerecon.run.pipeline import options_from_config
        from flamerecon.scenes import load_scene

        extra = [*([f"scene.downscale={args.downscale}"] if args.downscale else []),
                 *([f"grid.resolution={args.grid}"] if args.grid else [])]
        cfg = compose_train([*args.overrides, *extra, "calibration.refine=none", "projector.backend=assembled"])
        options = options_from_config(cfg)
        scene = load_scene(cfg.scene)
        sampler = Sampler()
        assemble, transpose = projector.assemble, sparse.transpose_csr

        def assembling(*a, **k):  # the rays' chunks, then (inside from_csr) the transpose
            sampler.phase = "chunks"
            return assemble(*a, **k)

        def transposing(*a, **k):
            sampler.phase = "transpose"
            return transpose(*a, **k)

        projector.assemble, sparse.transpose_csr = assembling, transposing
        try:
            setup = build(scene, options)
        finally:
            projector.assemble, sparse.transpose_csr = assemble, transpose
        sampler.phase = "after"
        time.sleep(0.05)
        peaks = sampler.stop()
        cams = camera_subset(scene.cameras, setup.train)
        rays, _ = projector.camera_rays(cams, fit_pixels(options.projector.rays, setup.grid, cams, setup.hull,
                                                         setup.masks[setup.train]))
        estimate = projector.assembled_memory(setup.grid, rays, setup.voxel_index, setup.step)
        A = setup.operator
        H, W = scene.image_size
        print(f"load average {os.getloadavg()[0]:.1f}; {W}x{H} images, grid {'x'.join(map(str, setup.grid.resolution))}")
        print(f"operator: {A.shape[0]} rays x {A.shape[1]} hull voxels, {A.nnz} nonzeros "
              f"(estimate {estimate.nnz}, {estimate.nnz / max(A.nnz, 1):.4f}x), A and A^T {16 * A.nnz / 2**30:.2f} GiB "
              f"(estimated peak above before: {estimate.peak_bytes / 2**30:.2f} GiB)")
        print(f"assembly {setup.assembly_seconds:.1f} s (the build {setup.seconds:.1f} s)")
        print("resident GiB: " + ", ".join(f"{phase} {peaks[phase]:.2f}" for phase in
                                           ("before", "chunks", "transpose", "after") if phase in peaks))

    return run_script(run, args.debug)


if __name__ == "__main__":
    raise SystemExit(main())
