"""What an image file's header says of its size, read without decoding it: a walk image of another
size than the camera's is skipped by it (:mod:`stereoseed.io.sequence`), and an image too large to
decode is refused by it before a byte of its pixels is read (:func:`refuse_huge_image`): a 389 KB
PNG may announce 20000 x 20000 pixels, 1.2 GB decoded."""
from __future__ import annotations

import math
import struct
from pathlib import Path

from stereoseed.errors import StereoseedError

__all__ = ["header_size", "refuse_huge_image", "recorded_image_size", "MAX_IMAGE_PIXELS", "MAX_IMAGE_SIDE"]

# the largest photos of today's cameras (a 102 MP medium-format sensor) pass; decoded as BGR this
# is 360 MB, and the features and the matching hold several float copies of an image at once
MAX_IMAGE_PIXELS = 120_000_000
# the longest side a JPEG can hold; an image size a calibration file records beyond it is a typo
MAX_IMAGE_SIDE = 65535


def recorded_image_size(values: object, where: str) -> tuple[int, int]:
    """(width, height) as a calibration file records it (two whole numbers within 1 ..
    MAX_IMAGE_SIDE, as JSON or FileStorage numbers), else a StereoseedError naming ``where``."""
    try:
        width, height = values  # type: ignore[misc]
        good = all(not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v == int(v)
                   and 1 <= v <= MAX_IMAGE_SIDE for v in (width, height))
    except (TypeError, ValueError):
        good = False
    if not good:
        raise StereoseedError(f"{where}: expected the image's width and height in pixels, two whole numbers from 1 "
                              f"to {MAX_IMAGE_SIDE}, got {str(values)[:60]}")
    return int(width), int(height)


def refuse_huge_image(path: str | Path) -> None:
    """Raise :class:`StereoseedError` when ``path``'s header (PNG, JPEG) announces more than
    :data:`MAX_IMAGE_PIXELS` pixels; other formats are left to the decoder's own limit."""
    size = header_size(path)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        w, h = size
        raise StereoseedError(f"{path}: {w}x{h} pixels ({w * h / 1e6:.0f} MP), more than the "
                              f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP stereoseed decodes; give a smaller image (scale it down)")


def header_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's or a JPEG's header, without decoding the image; None for
    other formats or a header that cannot be read (the decoder then says what is wrong)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                return (width, height) if width and height else None
            if head[:2] == b"\xff\xd8":
                fh.seek(2)
                return _jpeg_size(fh)
    except (OSError, struct.error):
        pass
    return None


# the start-of-frame markers (baseline, progressive, lossless, arithmetic) hold the image's size
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(fh) -> tuple[int, int] | None:
    """The size in a JPEG's frame header, reading its markers' segments from ``fh`` (after SOI)."""
    for _ in range(10_000):  # markers before the frame: a bound on a damaged file
        byte = fh.read(1)
        while byte == b"\xff":
            byte = fh.read(1)  # fill bytes
        if not byte:
            return None
        marker = byte[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # no length, no payload
            continue
        if marker in (0xD9, 0xDA):  # the end, or the scan before any frame header
            return None
        length = struct.unpack(">H", fh.read(2))[0]
        if marker in _JPEG_SOF:
            _, height, width = struct.unpack(">BHH", fh.read(5))
            return (width, height) if width and height else None
        if length < 2:
            return None
        fh.seek(length - 2, 1)
        nxt = fh.read(1)
        if nxt != b"\xff":
            return None
    return None
