"""An image file's EXIF orientation, and the image turned as it says (as viewers display it).

A phone or camera held on its side stores the pixels as the sensor read them and an EXIF
``Orientation`` tag (1-8) saying how to turn them for display. flamerecon reads every image as
displayed (:func:`displayed`), whichever format carries the tag (JPEG's APP1 segment, PNG's
``eXIf`` chunk, WebP's ``EXIF`` chunk, a TIFF's first directory): a calibration made on the
images as a viewer shows them fits them; one made on the stored pixels is refused on the size
(:func:`~flamerecon.scenes.calibration.check_image_size` names the orientation).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

#: the EXIF tag of the orientation
ORIENTATION_TAG = 0x0112
#: orientation -> what it does to the stored image for display, in words
TURNS = {1: "upright", 2: "mirrored left-right", 3: "rotated 180 degrees", 4: "mirrored top-bottom",
         5: "mirrored along its main diagonal", 6: "rotated 90 degrees clockwise",
         7: "mirrored along its other diagonal", 8: "rotated 90 degrees counter-clockwise"}
#: bytes read from the start of a file when looking for the tag (EXIF sits near the start)
HEAD_BYTES = 1 << 18


def _tiff_orientation(data: bytes) -> int:
    """The orientation in a TIFF structure (an EXIF block or a TIFF file), 1 when absent."""
    if len(data) < 8 or data[:2] not in (b"II", b"MM"):
        return 1
    order = "<" if data[:2] == b"II" else ">"
    (offset,) = struct.unpack(order + "I", data[4:8])
    if offset + 2 > len(data):
        return 1
    (count,) = struct.unpack(order + "H", data[offset:offset + 2])
    for k in range(count):
        entry = data[offset + 2 + 12 * k: offset + 14 + 12 * k]
        if len(entry) < 12:
            break
        tag, kind = struct.unpack(order + "HH", entry[:4])
        if tag == ORIENTATION_TAG and kind == 3:  # SHORT
            (value,) = struct.unpack(order + "H", entry[8:10])
            return value if value in TURNS else 1
    return 1


def _jpeg_exif(data: bytes) -> bytes | None:
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no EXIF before the pixels
            return None
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        segment = data[pos + 4:pos + 2 + length]
        if marker == 0xE1 and segment[:6] == b"Exif\0\0":
            return segment[6:]
        pos += 2 + length
    return None


def _chunks(data: bytes, start: int, big_endian: bool, header: int):
    """(kind, body) of each chunk of a PNG (lengths big-endian, CRC after) or a RIFF/WebP file."""
    pos = start
    while pos + 8 <= len(data):
        if big_endian:
            (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        else:
            kind, (length,) = data[pos:pos + 4], struct.unpack("<I", data[pos + 4:pos + 8])
        yield kind, data[pos + 8:pos + 8 + length]
        pos += 8 + length + header + (0 if big_endian else length % 2)


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation (1-8) of the image file ``path``; 1 where it has none or cannot be
    read (it is then displayed as stored)."""
    try:
        with open(path, "rb") as f:
            data = f.read(HEAD_BYTES)
    except OSError:
        return 1
    if data[:2] == b"\xff\xd8":
        block = _jpeg_exif(data)
        return 1 if block is None else _tiff_orientation(block)
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        block = next((body for kind, body in _chunks(data, 8, True, 4) if kind == b"eXIf"), None)
        return 1 if block is None else _tiff_orientation(block)
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        block = next((body for kind, body in _chunks(data, 12, False, 0) if kind == b"EXIF"), None)
        return 1 if block is None else _tiff_orientation(block[6:] if block[:6] == b"Exif\0\0" else block)
    return _tiff_orientation(data)


def displayed(image: np.ndarray, orientation: int) -> np.ndarray:
    """``image`` (H, W[, C]) as stored, turned as the EXIF ``orientation`` says for display."""
    if orientation in (5, 6, 7, 8):
        image = np.swapaxes(image, 0, 1)  # transposed: orientation 5
        if orientation == 6:
            image = image[:, ::-1]
        elif orientation == 7:
            image = image[::-1, ::-1]
        elif orientation == 8:
            image = image[::-1]
    elif orientation == 2:
        image = image[:, ::-1]
    elif orientation == 3:
        image = image[::-1, ::-1]
    elif orientation == 4:
        image = image[::-1]
    return np.ascontiguousarray(image)
