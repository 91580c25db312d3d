"""Image files for tests of the map loaders: a PNG whose header claims any size."""

from __future__ import annotations

import struct
import zlib

__all__ = ["png_declaring"]


def png_declaring(width: int, height: int) -> bytes:
    """A tiny PNG (a few dozen bytes) whose header declares ``width`` x ``height`` pixels: a loader must refuse
    it by its header, before decoding or allocating the image."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + \
        chunk(b"IEND", b"")
