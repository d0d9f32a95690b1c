"""The camera plan's picture: the rig and the ranked candidate cameras seen from above (looking
down the scene's up axis), each candidate coloured by the share of the confidence volume's
variance it is predicted to remove, the best ones numbered by rank, world azimuths marked."""

from __future__ import annotations

import cv2
import numpy as np

from flamerecon.geometry.axes import ground_frame
from flamerecon.outputs.figures import to_rgb8

#: picture size (pixels) and the strip for the title, and how many candidates get a rank number
SIZE_PX, TITLE_PX, NUMBERED = 520, 36, 5


def camera_plan_figure(up, box_corners, fitted: dict[str, np.ndarray], held: dict[str, np.ndarray],
                       candidates: np.ndarray, shares: np.ndarray, title: str = "") -> np.ndarray:
    """(H, W, 3) uint8: the box (``box_corners`` (8, 3) world), the fitted cameras (white
    dots, named; ``fitted``: name -> centre (3,)), the held-out ones (grey squares), and the
    candidate camera centres (N, 3) coloured by ``shares`` (N,) (fraction of the total
    variance removed, inferno, colour bar on the right) with the best :data:`NUMBERED` numbered
    by rank; seen from above along ``up`` (3,), the scene's up axis: world azimuth 0 to the
    right and 90 upwards (:func:`~flamerecon.geometry.axes.ground_frame`), marked on a ring with
    the world axes they lie along."""
    up = np.asarray(up, np.float64)
    everything = np.vstack([box_corners, *fitted.values(), *held.values(), candidates])
    centre = np.asarray(box_corners, np.float64).mean(0)
    first, second = ground_frame(up)

    def flat(p: np.ndarray) -> np.ndarray:
        d = np.asarray(p, np.float64) - centre
        return np.stack([d @ first, d @ second], -1)

    reach = float(np.abs(flat(everything)).max()) or 1.0
    span = reach * 1.3
    plot = SIZE_PX - 40

    def pixel(p: np.ndarray) -> tuple[int, int]:
        u, v = flat(p)
        return round(float(20 + (u / span + 1) * plot / 2)), round(float(TITLE_PX + 20 + (1 - v / span) * plot / 2))

    bar_w = 70
    image = np.zeros((SIZE_PX + TITLE_PX, SIZE_PX + bar_w, 3), np.uint8)
    hull = cv2.convexHull(np.array([pixel(c) for c in box_corners], np.int32))
    cv2.polylines(image, [hull], True, (120, 160, 255), 1, cv2.LINE_AA)
    top = float(shares.max()) if shares.size and shares.max() > 0 else 1.0
    colours = to_rgb8(np.asarray(shares, np.float32)[None, None, :], top)[0] if shares.size else np.zeros((0, 3))
    order = np.argsort(-shares)
    for rank, n in enumerate(order):
        x, y = pixel(candidates[n])
        cv2.circle(image, (x, y), 7, tuple(int(c) for c in colours[n]), -1, cv2.LINE_AA)
        cv2.circle(image, (x, y), 7, (90, 90, 90), 1, cv2.LINE_AA)
        if rank < NUMBERED:
            cv2.putText(image, str(rank + 1), (x + 9, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                        cv2.LINE_AA)
    for names, colour, square in ((fitted, (255, 255, 255), False), (held, (150, 150, 150), True)):
        for name, p in names.items():
            x, y = pixel(p)
            if square:
                cv2.rectangle(image, (x - 5, y - 5), (x + 5, y + 5), colour, -1)
            else:
                cv2.circle(image, (x, y), 5, colour, -1, cv2.LINE_AA)
            cv2.putText(image, name, (x + 8, y - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    cv2.circle(image, pixel(centre), round(plot / 2 * reach / span), (70, 70, 70), 1, cv2.LINE_AA)
    for angle in (0, 90, 180, 270):
        a = np.radians(angle)
        direction = np.cos(a) * first + np.sin(a) * second
        x, y = pixel(centre + direction * reach * 1.15)
        label = f"{angle} deg" + (f" ({axis_name_of(direction)})" if axis_name_of(direction) else "")
        size = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.36, 1)[0][0]
        x -= {0: 0, 90: size // 2, 180: size, 270: size // 2}[angle]  # 0 deg to the right, 90 up
        x = min(max(x, 2), SIZE_PX - size - 2)
        cv2.putText(image, label, (x, min(max(y + 4, TITLE_PX + 12), SIZE_PX + TITLE_PX - 4)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.36, (170, 170, 170), 1, cv2.LINE_AA)
    for row, text in enumerate((title or "where to put the next camera (top view)",
                                ("dots: fitted cameras, squares: held out, circles: candidates (1 = best); "
                                 f"seen from above ({axis_name_of(up) or 'up'})"))):
        cv2.putText(image, text, (6, 14 + 16 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.42 if row == 0 else 0.36,
                    (255, 255, 255), 1, cv2.LINE_AA)
    ramp = np.linspace(top, 0.0, plot, dtype=np.float32)[:, None].repeat(12, 1)
    y0, x0 = TITLE_PX + 20, SIZE_PX + 8
    image[y0:y0 + plot, x0:x0 + 12] = to_rgb8(ramp[None], top)
    for y, text in ((y0 + 8, f"{100 * top:.2g}%"), (y0 + plot, "0%")):
        cv2.putText(image, text, (x0 + 15, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(image, "variance", (x0 - 4, y0 + plot + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1,
                cv2.LINE_AA)
    cv2.putText(image, "removed", (x0 - 4, y0 + plot + 28), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1,
                cv2.LINE_AA)
    return image


def axis_name_of(direction: np.ndarray) -> str:
    """``+x`` ... ``-z`` for a unit direction along a world axis, else an empty string."""
    k = int(np.abs(direction).argmax())
    return ("+" if direction[k] > 0 else "-") + "xyz"[k] if abs(direction[k]) > 0.999 else ""
