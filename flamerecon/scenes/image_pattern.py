"""Which image files belong to which camera and frame, for the converters
(``scripts/convert_capture.py --images DIR [--pattern ...]``): by a camera's name (an image,
video or frame folder named after it), or by a file-name pattern over a flat folder such as
``{camera}_t{frame:04d}.png``.
"""

from __future__ import annotations

import re
from pathlib import Path

from flamerecon.scenes.base import SceneError
from flamerecon.scenes.frames import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS

_FIELD = re.compile(r"\{([^{}:]*)(?::([^{}]*))?\}")

#: a camera's images: one file (an image, a video or a frame folder), or {frame: file}
Images = Path | dict[int, Path]


class ImagePattern:
    """A file-name pattern with the fields ``{camera}`` (required) and ``{frame}`` (optional,
    with an integer format such as ``{frame:04d}``); any other text is literal. Bad patterns
    raise ValueError with what to write instead."""

    def __init__(self, text: str) -> None:
        self.text = text
        if "/" in text or "\\" in text:
            raise ValueError(f"'{text}' names a subfolder; give a file-name pattern of a flat folder")
        parts, fields, pos = [], [], 0
        self.frame_format: str | None = None  # the format of {frame}: "04d", or "d"
        for match in _FIELD.finditer(text):
            parts.append(re.escape(text[pos:match.start()]))
            name, spec = match.group(1), match.group(2)
            if name not in ("camera", "frame"):
                raise ValueError(f"'{text}': unknown field {{{name}}}; use {{camera}} and {{frame}} (e.g. "
                                 "'{camera}_t{frame:04d}.png')")
            if name in fields:
                raise ValueError(f"'{text}': {{{name}}} appears twice")
            if name == "frame" and spec is not None and not re.fullmatch(r"0?\d*d", spec):
                raise ValueError(f"'{text}': {{frame:{spec}}} is not an integer format; write e.g. {{frame:04d}}")
            fields.append(name)
            if name == "frame":
                self.frame_format = spec or "d"
            parts.append(r"(?P<camera>.+?)" if name == "camera" else r"(?P<frame>\d+)")
            pos = match.end()
        parts.append(re.escape(text[pos:]))
        if "camera" not in fields:
            raise ValueError(f"'{text}' has no {{camera}} field; e.g. '{{camera}}_t{{frame:04d}}.png'")
        self.regex = re.compile("".join(parts))

    @property
    def has_frames(self) -> bool:
        return self.frame_format is not None

    def match(self, name: str) -> tuple[str, int | None] | None:
        """(camera, frame or None) of a file name, or None when it does not fit the pattern (a
        frame written otherwise than its format, e.g. '1' for {frame:04d}, does not)."""
        found = self.regex.fullmatch(name)
        if found is None:
            return None
        if not self.has_frames:
            return found["camera"], None
        frame = int(found["frame"])
        return (found["camera"], frame) if format(frame, self.frame_format) == found["frame"] else None

    def scan(self, folder: Path) -> dict[str, Images]:
        """{camera: its file, or {frame: file}} of the files in ``folder`` that fit."""
        found: dict[str, dict] = {}
        for path in sorted(folder.iterdir()):
            hit = self.match(path.name) if path.is_file() else None
            if hit is None:
                continue
            camera, frame = hit
            if frame in found.setdefault(camera, {}):
                raise SceneError(f"{folder}: {found[camera][frame].name} and {path.name} are both camera "
                                 f"'{camera}'{'' if frame is None else f' frame {frame}'} by --pattern "
                                 f"'{self.text}'; keep one")
            found[camera][frame] = path
        return {camera: files.get(None, files) for camera, files in found.items()}


def camera_images(names: list[str], folder: Path, pattern: ImagePattern | None) -> dict[str, Images]:
    """Each camera's images in ``folder``: by ``pattern``, else a file or frame folder named
    after the camera (NAME.png, NAME.mp4, NAME/); a camera without any is refused."""
    if not folder.is_dir():
        raise SceneError(f"{folder}: the images folder does not exist; give it with --images DIR")
    if pattern is not None:
        found = pattern.scan(folder)
        missing = [n for n in names if n not in found]
        if missing:
            seen = ", ".join(sorted(found)[:8]) or "none"
            raise SceneError(f"{folder}: no file fits --pattern '{pattern.text}' for camera '{missing[0]}' "
                             f"(cameras found by it: {seen}); check the pattern against the file names")
        return {n: found[n] for n in names}
    out = {}
    for name in names:
        candidates = [folder / name] + [folder / f"{name}{ext}" for ext in (*IMAGE_EXTENSIONS, *VIDEO_EXTENSIONS)]
        hit = next((c for c in candidates if c.exists()), None)
        if hit is None:
            raise SceneError(f"{folder}: no image of camera '{name}' ({name}.png, {name}.mp4 or a frame folder "
                             f"{name}/); name a flat folder's files with --pattern, e.g. '{{camera}}_t{{frame:04d}}.png'")
        out[name] = hit
    return out


def first_file(images: Images) -> Path:
    """The file of a camera's first frame (its image, video or frame folder when it has one)."""
    return images if isinstance(images, Path) else images[min(images)]
