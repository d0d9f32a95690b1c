"""The web viewer: a viser server (the library nerfstudio's viewer is built on) that renders the
density with flamerecon's own renderer from each browser's camera, coarse while the camera
moves and at the browser's resolution when it rests, behind the capture's cameras (frustums
with their captured images, held-out ones red and labelled with their scores), the box, and
toggles for the iso-surface mesh and three slice planes with their colour bar; an exposure
control and, for a sequence, a time slider.

A render is the emission's line integral (:func:`~flamerecon.operators.projector.render_image`)
in the captured images' units, times 2^exposure, shown as the cameras record it
(:meth:`~flamerecon.scenes.Scene.to_recorded`), clipped to [0, 1]: at exposure 0 a held-out
camera's view looks like its capture. Needs ``pip install 'flamerecon[view]'``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from flamerecon.device import resolve_device
from flamerecon.errors import ConfigError
from flamerecon.geometry.cameras import camera_centers, cameras_to, intrinsics_matrix, make_cameras
from flamerecon.operators.projector import render_image
from flamerecon.outputs.export import voxel_size
from flamerecon.outputs.figures import brightest_index, to_display
from flamerecon.outputs.mesh import DEFAULT_ISO, iso_surface
from flamerecon.scenes.convert import quaternion_matrix
from flamerecon.viewer.address import COMMAND_LINE, Fields, listen_address, start_viser
from flamerecon.viewer.content import SCORE_KEYS, ViewFrame, frames_of

#: seconds the camera must rest before the full-resolution render
REST_S = 0.3
#: the coarse render's size: the browser's divided by this
COARSE_FACTOR = 4
#: the longest side of a full render, pixels (a larger browser window is upscaled)
MAX_SIDE = 1280
#: rows rendered at a time at full resolution; a camera move between two bands restarts
BAND_ROWS = 96
HELDOUT_COLOUR, TRAIN_COLOUR, BOX_COLOUR = (230, 60, 60), (70, 130, 230), (150, 150, 150)
DENSITY_UNIT = "image units per world unit"
_INSTALL_HINT = "the viewer needs viser: pip install 'flamerecon[view]'"


def viser_module():
    """The ``viser`` package, or a ConfigError saying how to install it."""
    try:
        import viser
    except ImportError as err:
        raise ConfigError(f"flamerecon view: {_INSTALL_HINT} ({err})") from None
    return viser


def browser_camera(wxyz, position, fov: float, width: int, height: int):
    """The kornia camera (batch of 1) of a browser's view: viser's camera-to-world rotation
    ``wxyz`` and ``position`` (OpenCV axes: x right, y down, z forward), vertical field of view
    ``fov`` in radians, an image ``width`` x ``height``, principal point at its centre."""
    rotation = quaternion_matrix(*(float(v) for v in wxyz))
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation.T
    world_to_camera[:3, 3] = -rotation.T @ np.asarray(position, float)
    focal = 0.5 * height / math.tan(0.5 * fov)
    K = intrinsics_matrix(focal, focal, width / 2, height / 2)
    return make_cameras(K, torch.from_numpy(world_to_camera)[None], height, width)


def rotation_wxyz(rotation: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) as a unit quaternion (w, x, y, z)."""
    m = np.asarray(rotation, float)
    w = math.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def display_image(linear: torch.Tensor, frame: ViewFrame, exposure: float) -> np.ndarray:
    """A render (C, H, W) in the captures' linear units as the browser shows it: times
    2^``exposure``, in the cameras' recorded units, clipped: (H, W, 3) uint8."""
    shown = to_display(frame.scene.to_recorded(linear.float() * 2.0 ** exposure))
    return np.ascontiguousarray((shown.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8))


def capture_thumbnail(image: torch.Tensor) -> np.ndarray:
    """A captured image (C, H, W) in [0, 1] for its frustum: (H, W, 4) uint8 RGBA, its dark
    background see-through (opacity 4 x the brightest channel, at least 0.3) so that the render
    behind it shows."""
    rgb = to_display(image).permute(1, 2, 0).numpy()
    alpha = np.clip(4 * rgb.max(-1, keepdims=True), 0.3, 1.0)
    return np.ascontiguousarray((np.concatenate([rgb, alpha], -1) * 255 + 0.5).astype(np.uint8))


def colour_bar(vmax: float, unit: str = DENSITY_UNIT, width: int = 256) -> np.ndarray:
    """The slices' colour bar: the inferno ramp from 0 to ``vmax`` with its ends labelled and
    the unit below, (64, width, 3) uint8 RGB."""
    bar = np.zeros((64, width, 3), np.uint8)
    bar[:] = 255
    ramp = np.linspace(0, 255, width - 20).astype(np.uint8)[None].repeat(16, 0)
    bar[6:22, 10:width - 10] = cv2.applyColorMap(ramp, cv2.COLORMAP_INFERNO)[..., ::-1]
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    cv2.putText(bar, "0", (8, 38), font, 0.4, black, 1, cv2.LINE_AA)
    top = f"{vmax:.3g}"
    cv2.putText(bar, top, (width - 12 - 7 * len(top), 38), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.putText(bar, f"density, {unit}", (8, 56), font, 0.38, black, 1, cv2.LINE_AA)
    return bar


def scene_note(scene) -> str:
    """The scene's up axis and length unit, as the panel says them."""
    unit = "world units of unknown length" if scene.unit is None else f"1 world unit = {scene.unit:g} m"
    return f"Up: {scene.up}; lengths: {unit}."


def slice_points(frame: ViewFrame) -> tuple[np.ndarray, np.ndarray, float]:
    """The three planes through the middle of the density's brightest region (channels summed,
    :func:`~flamerecon.outputs.figures.brightest_index`) as points at
    their voxel centres (N, 3) world xyz, their inferno colours (N, 3) uint8 and the largest
    value on them (the colour bar's top)."""
    total = frame.density.sum(0).float().cpu().numpy()  # (nz, ny, nx)
    lo, hi = np.asarray(frame.grid.bbox_min, float), np.asarray(frame.grid.bbox_max, float)
    size = voxel_size(lo, hi, total.shape)
    i, j, k = brightest_index(total[None])
    nz, ny, nx = total.shape
    kk, jj, ii = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    on = (ii == i) | (jj == j) | (kk == k)
    values = total[on]
    vmax = float(values.max()) or 1.0
    points = lo + (np.stack([ii[on], jj[on], kk[on]], 1) + 0.5) * size
    levels = np.clip(values / vmax * 255, 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(levels[:, None], cv2.COLORMAP_INFERNO)[:, 0, ::-1]
    return points.astype(np.float32), np.ascontiguousarray(colours), vmax


def scores_markdown(frame: ViewFrame) -> str:
    """The held-out cameras' scores as a markdown table, and the training views' mean PSNR."""
    lines = [f"**{frame.label}**: held-out scores", "", "| camera | " + " | ".join(n for _, n in SCORE_KEYS) + " |",
             "|---" * (len(SCORE_KEYS) + 1) + "|"]
    for name, values in frame.scores.items():
        cells = [f"{values[k]:.3g}" if isinstance(values.get(k), (int, float)) else "-" for k, _ in SCORE_KEYS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if frame.train_psnr is not None:
        lines += ["", f"training views: mean PSNR {frame.train_psnr:.2f} dB ({len(frame.train)} cameras)"]
    return "\n".join(lines)


@dataclass
class RenderRecord:
    """One render sent to a browser: its client, ``coarse`` or ``full``, size and seconds."""

    client: int
    kind: str
    height: int
    width: int
    seconds: float


class ClientView:
    """One browser: renders its camera's view in a thread of its own, coarse at once on every
    camera move, then at full resolution once the camera rests for :data:`REST_S`."""

    def __init__(self, viewer: Viewer, client) -> None:
        self.viewer, self.client = viewer, client
        self.stamp = 0
        self.wake = threading.Event()
        self.closed = False
        self.last: torch.Tensor | None = None  # the last render (C, H, W), linear
        self.thread = threading.Thread(target=self._loop, name=f"flamerecon-view-{client.client_id}", daemon=True)
        self.thread.start()

    def request(self) -> None:
        self.stamp += 1
        self.wake.set()

    def close(self) -> None:
        self.closed = True
        self.wake.set()

    def redisplay(self) -> None:
        """Show the last render again (a new exposure), else render."""
        if self.last is None:
            self.request()
        else:
            self._show(self.last)

    def _loop(self) -> None:
        while not self.closed:
            if not self.wake.wait(0.5):
                continue
            self.wake.clear()
            if self.closed:
                return
            stamp = self.stamp
            try:
                self._render(stamp, coarse=True)
                if self.wake.wait(REST_S) or self.closed:
                    continue  # the camera moved again: start over
                self._render(stamp, coarse=False)
            except (RuntimeError, OSError, ValueError) as err:  # a browser gone mid-render; the server lives on
                if not self.closed:
                    self.viewer.log(f"render for browser {self.client.client_id} failed: {err}")

    def _render(self, stamp: int, coarse: bool) -> None:
        camera = self.client.camera
        width, height = int(camera.image_width), int(camera.image_height)
        if width < 2 or height < 2:
            width, height = 640, 480
        scale = min(1.0, MAX_SIDE / max(width, height)) / (COARSE_FACTOR if coarse else 1)
        width, height = max(8, round(width * scale)), max(8, round(height * scale))
        frame = self.viewer.frame
        cams = browser_camera(camera.wxyz, camera.position, float(camera.fov), width, height)
        start = time.perf_counter()
        volume = frame.density.to(self.viewer.device).float()
        step = 1.0 if coarse else 0.5
        bands = []
        for row in range(0, height, height if coarse else BAND_ROWS):
            rows = min(BAND_ROWS if not coarse else height, height - row)
            band = cams.intrinsics.clone()
            band[:, 1, 2] -= row
            piece = type(cams)(band, cams.extrinsics, torch.tensor([float(rows)]), cams.width)
            bands.append(render_image(volume, frame.grid, cameras_to(piece, volume.device), step)[0].cpu())
            if self.stamp != stamp or self.closed:
                return  # the camera moved: this view is stale
        image = torch.cat(bands, dim=1)
        self.last = image
        self._show(image)
        record = RenderRecord(self.client.client_id, "coarse" if coarse else "full", height, width,
                              time.perf_counter() - start)
        self.viewer.renders.append(record)
        self.viewer.status.content = (f"last render: {record.kind}, {width} x {height} px in {record.seconds:.2f} s "
                                      f"on {self.viewer.device}")

    def _show(self, image: torch.Tensor) -> None:
        self.client.scene.set_background_image(display_image(image, self.viewer.frame, self.viewer.exposure),
                                               format="jpeg", jpeg_quality=92)


class Viewer:
    """``flamerecon view``'s server on ``host:port`` (the next free port if that one is taken)
    for a Reconstruction, a loaded Run, a run folder or a multirun folder; :attr:`url` is where
    a browser opens it, :meth:`stop` ends it. ``renders`` records every render sent. The host
    and port are checked before anything is loaded (:func:`~flamerecon.viewer.address.listen_address`;
    ``fields``: their names in its messages), and viser is started so that a failure to listen
    is a ConfigError, never a wait (:func:`~flamerecon.viewer.address.start_viser`)."""

    def __init__(self, source, host: str = "127.0.0.1", port: int = 8080, device: str = "auto",
                 iso: float = DEFAULT_ISO, log=print, fields: Fields = COMMAND_LINE) -> None:
        viser = viser_module()
        port = listen_address(host, port, fields)
        self.frames = frames_of(source, device)
        self.device = resolve_device(device, "view.device")
        self.log = log
        self.index, self.exposure, self.iso = 0, 0.0, float(iso)
        self.renders: list[RenderRecord] = []
        self.clients: dict[int, ClientView] = {}
        self.broken: set[int] = set()  # frames whose failure to load was said once
        self.frame = self.frames[0]
        self.server = start_viser(viser, host, listen_address(host, port, fields), fields)
        self.host = host
        self._gui()
        self.server.scene.set_up_direction(tuple(float(u) for u in self.frame.up))
        self._show_frame(0)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        """Where a browser on this machine opens it (an IPv6 address in brackets)."""
        host = "localhost" if self.host in ("127.0.0.1", "0.0.0.0", "::", "") else self.host
        return f"http://[{host}]:{self.port}" if ":" in host else f"http://{host}:{self.port}"

    def stop(self) -> None:
        """Close every browser's render thread and the server."""
        for view in list(self.clients.values()):
            view.close()
        self.server.stop()

    # -- the panel ---------------------------------------------------------------------------

    def _gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown("Drag to orbit, right-drag to pan, scroll to zoom; the density is rendered "
                         "by flamerecon for your view (coarse while it moves). Red cameras are held out. "
                         + scene_note(self.frame.scene))
        if len(self.frames) > 1:
            self.time = gui.add_slider("time (frame)", min=0, max=len(self.frames) - 1, step=1, initial_value=0)
            self.time_label = gui.add_markdown(self.frames.labels[0])
            self.time.on_update(lambda _: self._show_frame(int(self.time.value)))
        self.exposure_slider = gui.add_slider("exposure (stops)", min=-6.0, max=6.0, step=0.25, initial_value=0.0)
        self.exposure_slider.on_update(lambda _: self._set_exposure(float(self.exposure_slider.value)))
        self.show_cameras = gui.add_checkbox("cameras", initial_value=True)
        self.show_cameras.on_update(lambda _: self._cameras())
        self.show_mesh = gui.add_checkbox("iso-surface", initial_value=False)
        self.iso_slider = gui.add_slider("iso level (x peak)", min=0.02, max=0.9, step=0.01, initial_value=self.iso)
        self.show_mesh.on_update(lambda _: self._mesh())
        self.iso_slider.on_update(lambda _: self._mesh())
        self.show_slices = gui.add_checkbox("slices", initial_value=False)
        self.show_slices.on_update(lambda _: self._slices())
        self.bar = gui.add_image(colour_bar(1.0), label="slices' colour bar", visible=False)
        self.scores = gui.add_markdown("")
        self.status = gui.add_markdown("")

    def _set_exposure(self, exposure: float) -> None:
        self.exposure = exposure
        for view in list(self.clients.values()):
            view.redisplay()

    # -- the 3D scene ------------------------------------------------------------------------

    def _show_frame(self, index: int) -> None:
        """Show frame ``index``; one that cannot be loaded (its run folder broken while viewed)
        leaves the last frame shown, says why in the panel and once in the log."""
        label = self.frames.labels[index]
        self.status.content = f"loading {label} ..."
        try:
            frame = self.frames[index]
        except Exception as err:  # noqa: BLE001 - any failure of one frame; the server lives on
            message = f"{label} cannot be shown: {' '.join(str(err).split()) or type(err).__name__}"
            self.status.content = f"{message}; still showing {self.frames.labels[self.index]}"
            if index not in self.broken:
                self.broken.add(index)
                self.log(f"flamerecon view: {message}")
            return
        self.index, self.frame = index, frame
        if len(self.frames) > 1:
            self.time_label.content = self.frames.labels[index]
        self.scores.content = scores_markdown(self.frame)
        self.status.content = ""
        self._box()
        self._cameras()
        self._mesh()
        self._slices()
        for view in list(self.clients.values()):
            view.request()

    def _box(self) -> None:
        lo, hi = np.asarray(self.frame.grid.bbox_min, float), np.asarray(self.frame.grid.bbox_max, float)
        corners = np.array([[lo[0] if a == 0 else hi[0], lo[1] if b == 0 else hi[1], lo[2] if c == 0 else hi[2]]
                            for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        edges = [(p, q) for p in range(8) for q in range(p + 1, 8) if (p ^ q).bit_count() == 1]
        segments = np.stack([corners[[p, q]] for p, q in edges]).astype(np.float32)
        self.server.scene.add_line_segments("/box", segments, BOX_COLOUR, thickness=2, thickness_units="screen")

    def _cameras(self) -> None:
        frame, scene = self.frame, self.frame.scene
        visible = bool(self.show_cameras.value)
        centres = camera_centers(scene.cameras).double().cpu().numpy()
        box_centre = (np.asarray(frame.grid.bbox_min) + np.asarray(frame.grid.bbox_max)) / 2
        size = 0.1 * float(np.median(np.linalg.norm(centres - box_centre, axis=1)))
        H, W = scene.image_size
        for v, name in enumerate(scene.views):
            w2c = scene.cameras.extrinsics[v].double().cpu().numpy()
            fy = float(scene.cameras.intrinsics[v, 1, 1])
            held = v in frame.holdout
            thumb = cv2.resize(capture_thumbnail(scene.recorded_view(v)), (160, max(1, round(160 * H / W))),
                               interpolation=cv2.INTER_AREA)
            self.server.scene.add_camera_frustum(
                f"/cameras/{name}", fov=2 * math.atan(0.5 * H / fy), aspect=W / H, scale=size,
                color=HELDOUT_COLOUR if held else TRAIN_COLOUR, image=thumb, format="png", wxyz=rotation_wxyz(w2c[:3, :3].T),
                position=centres[v], visible=visible, thickness=2, thickness_units="screen")
            score = frame.scores.get(name, {})
            text = (f"{name}, held out: {score['psnr']:.2f} dB (black {score.get('psnr_black', float('nan')):.2f})"
                    if held and "psnr" in score else name)
            self.server.scene.add_label(f"/labels/{name}", text, position=centres[v], visible=visible)

    def _mesh(self) -> None:
        if not self.show_mesh.value:
            self.server.scene.add_mesh_simple("/iso_surface", np.zeros((3, 3), np.float32),
                                              np.zeros((1, 3), np.int32), visible=False)
            return
        density = self.frame.density.float().cpu().numpy()
        try:
            vertices, faces = iso_surface(density, self.frame.grid.bbox_min, self.frame.grid.bbox_max,
                                          float(self.iso_slider.value))
        except (ImportError, ConfigError) as err:
            self.status.content = f"iso-surface: {err}"
            return
        self.server.scene.add_mesh_simple("/iso_surface", vertices.astype(np.float32), faces.astype(np.int32),
                                          color=(255, 170, 60), opacity=0.6, side="double")

    def _slices(self) -> None:
        visible = bool(self.show_slices.value)
        self.bar.visible = visible
        if not visible:
            self.server.scene.add_point_cloud("/slices", np.zeros((1, 3), np.float32), (0, 0, 0), visible=False)
            return
        points, colours, vmax = slice_points(self.frame)
        size = float(voxel_size(self.frame.grid.bbox_min, self.frame.grid.bbox_max, self.frame.density.shape).min())
        self.server.scene.add_point_cloud("/slices", points, colours, point_size=size, point_shape="square",
                                          point_shading="flat")
        self.bar.image = colour_bar(vmax)

    # -- browsers ----------------------------------------------------------------------------

    def _connect(self, client) -> None:
        """A new browser starts behind the first held-out camera (1.5 times as far from the box
        centre, its frustum and score in view) with its field of view, looking at the box."""
        frame = self.frame
        first = frame.holdout[0] if frame.holdout else frame.train[0]
        cams = frame.scene.cameras
        centre = camera_centers(cams)[first].double().cpu().numpy()
        box_centre = (np.asarray(frame.grid.bbox_min) + np.asarray(frame.grid.bbox_max)) / 2
        H = frame.scene.image_size[0]
        with client.atomic():
            client.camera.up_direction = frame.up
            client.camera.position = box_centre + 1.5 * (centre - box_centre)
            client.camera.look_at = box_centre
            client.camera.fov = 2 * math.atan(0.5 * H / float(cams.intrinsics[first, 1, 1]))
        view = ClientView(self, client)
        self.clients[client.client_id] = view
        client.camera.on_update(lambda _: view.request())
        view.request()

    def _disconnect(self, client) -> None:
        view = self.clients.pop(client.client_id, None)
        if view is not None:
            view.close()

