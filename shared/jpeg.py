"""JPEG headers (and PNG's and BMP's), read before decoding: a header can claim any size up to 65535 x 65535 (PNG and
BMP more), and OpenCV allocates what it claims (or raises past 2**30 pixels). Services compare the claim with what the
image must be first."""

from __future__ import annotations

import cv2
import numpy as np

# start-of-frame markers (baseline, extended, progressive, lossless, ...); C4, C8 and CC are other segments
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's start-of-frame segment, or None when `data` has none (not a JPEG, or cut
    before it)."""
    if data[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            i += 2
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        if marker in _SOF:
            if i + 9 > n or length < 7:
                return None
            height = int.from_bytes(data[i + 5:i + 7], "big")
            width = int.from_bytes(data[i + 7:i + 9], "big")
            return width, height
        if marker == 0xDA or length < 2:  # image data before any frame header, or a broken length
            return None
        i += 2 + length
    return None


def png_bmp_size(data: bytes) -> tuple[str, int, int] | None:
    """("PNG" or "BMP", width, height) from a PNG's IHDR chunk or a BMP's info header, or None when `data` is neither
    (or is cut before its size)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return "PNG", int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] == b"BM" and len(data) >= 26:
        if int.from_bytes(data[14:18], "little") == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
            return "BMP", int.from_bytes(data[18:20], "little"), int.from_bytes(data[20:22], "little")
        # BITMAPINFOHEADER and later: 32-bit signed sizes, a negative height for rows stored top-down
        return "BMP", abs(int.from_bytes(data[18:22], "little", signed=True)), \
            abs(int.from_bytes(data[22:26], "little", signed=True))
    return None


def decode_grey(data: bytes, width: int, height: int, flags: int = cv2.IMREAD_GRAYSCALE, reduce: int = 1,
                what: str = "image") -> np.ndarray:
    """An image that must be `width` x `height` (each within `reduce` pixels: a camera's size, decoded at
    1/`reduce` by `flags`) decoded to grey; ValueError naming `what` for a JPEG, PNG or BMP whose header claims another
    size, an empty or corrupt file, or one OpenCV refuses. Other formats are decoded without the header check: their
    callers check the decoded size."""
    size = jpeg_size(data)
    if size is None and (not data or data[:2] == b"\xff\xd8"):
        raise ValueError(f"{what}: corrupt JPEG ({len(data)} bytes): no frame header")
    # PNG and BMP are decoded in full, however large: their headers are checked first as well
    claimed = ("JPEG", *size) if size is not None else png_bmp_size(data)
    if claimed is not None and (abs(claimed[1] - width) > reduce or abs(claimed[2] - height) > reduce):
        raise ValueError(f"{what}: {claimed[0]} is {claimed[1]}x{claimed[2]}, expected {width}x{height}")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        raise ValueError(f"{what}: image refused by the decoder ({str(exc).strip().splitlines()[-1]})") from None
    if img is None:
        raise ValueError(f"{what}: corrupt JPEG ({len(data)} bytes)" if size is not None or not data
                         else f"{what}: cannot decode image ({len(data)} bytes)")
    return img
