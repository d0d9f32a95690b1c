"""How examples/capture/ was made: the synthetic flame seen by five cameras, written as a capture
of one's own would be, in scene=opencv's format (docs/own_capture.md):

    python examples/capture/make_capture.py examples/capture

calibration.yaml (per camera K, R, t with x_cam = R x_world + t, and the box and held-out
camera), and per camera a frame folder NAME/000000.png (8-bit). A capture with videos puts
NAME.mp4 beside the file instead. ``tests/test_own_capture.py`` loads and reconstructs it.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

import flamerecon as fr


def main(out: Path) -> None:
    scene = fr.load_scene("synthetic", width=64, height=48, n_cameras=5, phantom_resolution=32)
    cameras = []
    for v, name in enumerate(scene.views):
        K = scene.cameras.intrinsics[v, :3, :3].double().numpy()
        K[:2, 2] -= 0.5  # OpenCV's pixel convention: pixel index k at coordinate k
        w2c = scene.cameras.extrinsics[v].double().numpy()
        cameras.append({"name": name, "K": K.round(6).tolist(), "R": w2c[:3, :3].round(9).tolist(),
                        "t": w2c[:3, 3].round(9).tolist(), "width": 64, "height": 48})
        image = (scene.images[v].permute(1, 2, 0).numpy().clip(0, 1) * 255 + 0.5).astype(np.uint8)
        (out / name).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / name / "000000.png"), image[..., ::-1])
    record = {"cameras": cameras, "bbox": [list(scene.bbox_min), list(scene.bbox_max)], "holdout": ["cam04"]}
    head = "# A tiny capture in scene=opencv's format (docs/own_capture.md); made by make_capture.py\n"
    (out / "calibration.yaml").write_text(head + yaml.safe_dump(record, sort_keys=False, default_flow_style=None))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
