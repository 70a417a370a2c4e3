"""An image file's size in pixels from its header, without decoding it (:func:`image_size`).

A 330 kB PNG can hold 20000 x 15000 pixels (a solid colour compresses a thousandfold): decoding it takes
minutes and gigabytes. The file's size says nothing of that; its header does, in a few bytes. So the
image sources read the header first and refuse more pixels than :data:`MAX_IMAGE_PIXELS` (or the
``--max-megapixels`` given) before the decoder sees the file.

Read here: PNG (IHDR), JPEG (the first SOF segment, found by skipping the segments before it, EXIF
thumbnails included), BMP, WebP (VP8, VP8L, VP8X), PNM (PBM/PGM/PPM, text header) and TIFF (the first
image directory). Any other file, or a header that does not parse, gives None: the caller then decodes
as before (bounded by the file's size only), and the decoder says what is wrong with it.
"""

from __future__ import annotations

import os
import stat
import struct
from pathlib import Path
from typing import BinaryIO

__all__ = ["MAX_IMAGE_PIXELS", "image_size", "pixel_limit_text"]

MAX_IMAGE_PIXELS = 50_000_000  # 50 MP: above any camera's frame (8K is 33 MP); --max-megapixels raises it

_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})  # TEM, RSTn: no length
_MAX_JPEG_SEGMENTS = 512  # the SOF comes after a few APPn/DQT/DHT/COM segments; this many is no JPEG


def pixel_limit_text(max_pixels: int) -> str:
    """``50`` for 50 000 000 (the ``--max-megapixels`` value that gives it)."""
    return f"{max_pixels / 1e6:g}"


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from ``path``'s header, or None (not a regular file, not a format read here, or a header
    that does not parse). Reads a few hundred bytes (a JPEG: its segment headers until the frame header)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # (a named pipe would block a plain open)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            return None
        stream = os.fdopen(fd, "rb")
    except OSError:
        os.close(fd)
        return None
    try:
        with stream:
            head = stream.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n"):
                return _png(head)
            if head.startswith(b"\xff\xd8"):
                return _jpeg(stream)
            if head.startswith(b"BM"):
                return _bmp(head)
            if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
                return _webp(head)
            if len(head) >= 2 and head[0:1] == b"P" and head[1:2] in b"123456":
                return _pnm(stream)
            if head[:4] in (b"II*\x00", b"MM\x00*"):
                return _tiff(stream, head)
    except (OSError, struct.error, ValueError):
        return None
    return None


def _positive(width: int, height: int) -> tuple[int, int] | None:
    return (width, height) if width > 0 and height > 0 else None


def _png(head: bytes) -> tuple[int, int] | None:
    if head[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return _positive(width, height)


def _jpeg(stream: BinaryIO) -> tuple[int, int] | None:
    stream.seek(2)
    for _ in range(_MAX_JPEG_SEGMENTS):
        byte = stream.read(1)
        if byte != b"\xff":
            return None
        marker = stream.read(1)
        while marker == b"\xff":  # fill bytes
            marker = stream.read(1)
        if not marker:
            return None
        code = marker[0]
        if code in _JPEG_STANDALONE:
            continue
        if code in (0xD9, 0xDA):  # end of image, or scan data before any frame header
            return None
        length = struct.unpack(">H", stream.read(2))[0]
        if length < 2:
            return None
        if code in _JPEG_SOF:
            _precision, height, width = struct.unpack(">BHH", stream.read(5))
            return _positive(width, height)
        stream.seek(length - 2, 1)
    return None


def _bmp(head: bytes) -> tuple[int, int] | None:
    header_size = struct.unpack("<I", head[14:18])[0]
    if header_size == 12:  # BITMAPCOREHEADER
        width, height = struct.unpack("<HH", head[18:22])
    elif header_size >= 40:
        width, height = struct.unpack("<ii", head[18:26])
    else:
        return None
    return _positive(width, abs(height))  # (a negative height: rows top-down)


def _webp(head: bytes) -> tuple[int, int] | None:
    chunk = head[12:16]
    if chunk == b"VP8 " and head[23:26] == b"\x9d\x01\x2a":
        width, height = struct.unpack("<HH", head[26:30])
        return _positive(width & 0x3FFF, height & 0x3FFF)
    if chunk == b"VP8L" and head[20:21] == b"\x2f":
        bits = struct.unpack("<I", head[21:25])[0]
        return _positive(1 + (bits & 0x3FFF), 1 + ((bits >> 14) & 0x3FFF))
    if chunk == b"VP8X":
        width = int.from_bytes(head[24:27], "little") + 1
        height = int.from_bytes(head[27:30], "little") + 1
        return _positive(width, height)
    return None


def _pnm(stream: BinaryIO) -> tuple[int, int] | None:
    """The two numbers after the magic (``P6``), across whitespace and ``#`` comments."""
    stream.seek(2)
    text = stream.read(1024)
    numbers: list[int] = []
    token = b""
    comment = False
    for value in text:
        char = bytes((value,))
        if comment:
            comment = char not in b"\r\n"
            continue
        if char == b"#":
            comment = True
        elif char.isspace():
            if token:
                numbers.append(int(token))
                token = b""
                if len(numbers) == 2:
                    return _positive(*numbers)
        elif char.isdigit():
            token += char
        else:
            return None
    return None


def _tiff(stream: BinaryIO, head: bytes) -> tuple[int, int] | None:
    order = "<" if head[:2] == b"II" else ">"
    offset = struct.unpack(order + "I", head[4:8])[0]
    stream.seek(offset)
    count = struct.unpack(order + "H", stream.read(2))[0]
    if count > 4096:
        return None
    sizes: dict[int, int] = {}
    entries = stream.read(12 * count)
    for k in range(count):
        tag, kind, _count = struct.unpack(order + "HHI", entries[12 * k : 12 * k + 8])
        if tag in (256, 257):
            if kind == 3:  # SHORT
                sizes[tag] = struct.unpack(order + "H", entries[12 * k + 8 : 12 * k + 10])[0]
            elif kind == 4:  # LONG
                sizes[tag] = struct.unpack(order + "I", entries[12 * k + 8 : 12 * k + 12])[0]
    if 256 in sizes and 257 in sizes:
        return _positive(sizes[256], sizes[257])
    return None
