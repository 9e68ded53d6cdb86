"""The visibility bitmap: per-pixel light visibility packed into bytes for the wire.

Seed 000 §3.2 stores, for every pixel, one 32-bit unsigned integer whose bit ``i`` is set when light ``i``
is unobstructed (Algorithm 3B-2 step 4.2.2: ``v |= 1 << i``; Algorithm 3B-1 step 4.2.1 tests ``v & (1 << i)``).
That caps a scene at 32 lights (seed 000 §6.2). This module packs an ``(H, W, L)`` bool array into three
layouts and back:

``paper32``
    Paper-faithful: one little-endian uint32 per pixel, bit ``i`` = light ``i``; 4 bytes per pixel whatever the
    light count (1920×1080 → 8,294,400 bytes, seed 000 §4.3.1 / §5.2). Refuses more than 32 lights.
``words32``
    The §6.2 limitation lifted ("sending multiple 32-bit visibility bitmasks"): ``ceil(L/32)`` little-endian
    uint32 words per pixel; word ``k`` bit ``j`` = light ``32k + j``. No bytes at all when ``L == 0``.
``packed8``
    Only what the scene needs: ``ceil(L/8)`` bytes per pixel; byte ``k`` bit ``j`` (LSB first) = light ``8k + j``.

Exact bit order, shared by every layout: light ``i`` lives in byte ``i // 8`` of the pixel's record, at bit
``i % 8`` counted from the least significant bit. Because words are little-endian, the first ``ceil(L/8)``
bytes of a ``words32``/``paper32`` record are exactly the ``packed8`` record; the remaining bytes are zero.
Pixels are stored row-major, row 0 (the top of the image) first, so row ``r`` of the image occupies bytes
``[r * row_bytes, (r + 1) * row_bytes)`` of the bitmap (the property :mod:`.wire` relies on for UDP).
"""
from __future__ import annotations

import numpy as np

from suite.errors import UserError

LAYOUTS = ("paper32", "words32", "packed8")

#: Seed 000 §3.2 / §6.2: the paper's bitmask is one 32-bit word.
PAPER_MAX_LIGHTS = 32


def check_layout(layout: str) -> str:
    if layout not in LAYOUTS:
        raise UserError(f"unknown visibility bitmap layout '{layout}' (choose from {', '.join(LAYOUTS)})")
    return layout


def bytes_per_pixel(layout: str, light_count: int) -> int:
    """Bytes one pixel's visibility record takes in ``layout`` for ``light_count`` lights."""
    check_layout(layout)
    if light_count < 0:
        raise UserError(f"light count must be >= 0, got {light_count}")
    if layout == "paper32":
        if light_count > PAPER_MAX_LIGHTS:
            # seed 000 §6.2: the paper's 32-bit mask holds at most 32 lights.
            raise UserError(
                f"layout 'paper32' holds at most {PAPER_MAX_LIGHTS} lights, the scene has {light_count}; "
                "use layout=words32 or layout=packed8"
            )
        return 4
    if layout == "words32":
        return 4 * (-(-light_count // 32))
    return -(-light_count // 8)


def bitmap_nbytes(width: int, height: int, light_count: int, layout: str) -> int:
    """Size in bytes of one frame's bitmap, e.g. 1920×1080, ≤ 32 lights, paper32 → 8,294,400."""
    return int(width) * int(height) * bytes_per_pixel(layout, light_count)


def pack(visibility: np.ndarray, layout: str) -> np.ndarray:
    """Packs an ``(H, W, L)`` bool array into the bitmap, returned as ``(H, W * bytes_per_pixel)`` uint8.

    Row ``r`` of the result is image row ``r``; see the module docstring for the bit order.
    """
    visibility = np.asarray(visibility)
    if visibility.ndim != 3:
        raise ValueError(f"visibility must be (H, W, L), got shape {visibility.shape}")
    height, width, light_count = visibility.shape
    bpp = bytes_per_pixel(layout, light_count)
    if light_count == 0:
        return np.zeros((height, width * bpp), dtype=np.uint8)
    vis = np.ascontiguousarray(visibility, dtype=bool).view(np.uint8)
    used = -(-light_count // 8)
    # Light i → byte i // 8, bit i % 8 from the LSB: v |= 1 << i (seed 000 Alg. 3B-2 step 4.2.2). The three
    # branches give the same bytes; they differ only in speed (np.packbits along a short axis is slow).
    if light_count % 8 == 0:
        records = np.packbits(vis.reshape(-1), bitorder="little").reshape(height, width, used)
    elif light_count < 8:
        plane = vis[:, :, 0].copy()
        for i in range(1, light_count):
            plane |= vis[:, :, i] << np.uint8(i)
        records = plane[:, :, None]
    else:
        records = np.packbits(vis, axis=-1, bitorder="little")
    if bpp == used:
        out = records
    elif used == 1 and bpp == 4:
        # One byte of lights in a little-endian uint32: widening the integer writes bytes 1..3 as zeros.
        out = records[:, :, 0].astype("<u4").view(np.uint8).reshape(height, width, 4)
    else:
        out = np.zeros((height, width, bpp), dtype=np.uint8)
        out[:, :, :used] = records
    return out.reshape(height, width * bpp)


class DeviceBitmap:
    """A packed bitmap on a tracer's device (:mod:`suite.core.device`): the bytes of :func:`pack` in little-endian
    uint32 words (``data``, padded to whole words). ``to_host()`` is the explicit read-back: exactly ``pack``'s
    ``(H, W * bytes_per_pixel)`` uint8 array, and its byte count."""

    def __init__(self, device, width: int, height: int, light_count: int, layout: str, data):
        self.device, self.width, self.height = device, int(width), int(height)
        self.light_count, self.layout, self.data = int(light_count), layout, data
        self.bytes_per_pixel = bytes_per_pixel(layout, light_count)

    @property
    def nbytes(self) -> int:
        return self.width * self.height * self.bytes_per_pixel

    def to_host(self, with_bytes: bool = False):
        if self.nbytes == 0:
            out = np.zeros((self.height, 0), np.uint8)
            return (out, 0) if with_bytes else out
        copy = self.device.to_host(self.data, np.uint32, with_bytes=True)
        out = copy.array.view(np.uint8)[:self.nbytes].reshape(self.height, self.width * self.bytes_per_pixel)
        return (out, copy.nbytes) if with_bytes else out


def pack_device(visibility, layout: str) -> DeviceBitmap:
    """:func:`pack` on the device, from a :class:`suite.core.device.DeviceVisibility` (words of bits, as the
    visibility pass makes them). ``paper32`` and ``words32`` records are those words already (the same bytes); for
    ``packed8`` (and ``paper32`` without lights) one gather kernel moves each pixel's used bytes into place."""
    dev = visibility.device
    dr, U = dev.dr, dev.UInt32
    light_count = visibility.lights
    bpp = bytes_per_pixel(layout, light_count)
    width, height = visibility.width, visibility.height
    if bpp == visibility.bytes_per_pixel and bpp > 0:
        return DeviceBitmap(dev, width, height, light_count, layout, visibility.data)
    n_bytes = width * height * bpp
    if n_bytes == 0:
        return DeviceBitmap(dev, width, height, light_count, layout, dr.zeros(U, 1))
    src_bpp = visibility.bytes_per_pixel
    out_words = -(-n_bytes // 4)
    w = dev.arange(out_words)
    word = dr.zeros(U, out_words)
    used = -(-light_count // 8)
    for b in range(4):
        q = w * 4 + b  # output byte
        pixel = q // dev.opaque(U, bpp)
        j = q - pixel * bpp  # byte of the pixel's record
        take = (q < dev.opaque(U, n_bytes)) & (j < used)
        src = pixel * src_bpp + j  # the same byte in the source record
        value = dr.gather(U, visibility.data, src >> 2, take)
        byte = (value >> ((src & 3) << 3)) & 0xFF
        word = word | dr.select(take, byte << (8 * b), U(0))
    dev.eval(word)
    return DeviceBitmap(dev, width, height, light_count, layout, word)


def unpack(bitmap: np.ndarray, width: int, light_count: int, layout: str) -> np.ndarray:
    """Inverse of :func:`pack`: ``(H, W * bytes_per_pixel)`` uint8 (or flat bytes) → ``(H, W, L)`` bool."""
    bpp = bytes_per_pixel(layout, light_count)
    raw = np.frombuffer(bitmap, dtype=np.uint8) if isinstance(bitmap, (bytes, bytearray, memoryview)) else bitmap
    raw = np.asarray(raw, dtype=np.uint8)
    if bpp == 0:
        height = raw.shape[0] if raw.ndim == 2 else 0
        return np.zeros((height, width, 0), dtype=bool)
    if raw.size % (width * bpp):
        raise ValueError(f"bitmap of {raw.size} bytes is not a whole number of {width}-pixel rows of {bpp} bytes")
    records = np.ascontiguousarray(raw).reshape(-1, width, bpp)
    height = records.shape[0]
    if light_count == 0:
        return np.zeros((height, width, 0), dtype=bool)
    used = -(-light_count // 8)
    # Only the bytes that hold lights are read (paper32 with 3 lights: 1 of 4 bytes per pixel).
    if light_count % 8 == 0 and used == bpp:
        bits = np.unpackbits(records.reshape(-1), bitorder="little").reshape(height, width, light_count)
    elif light_count < 8:
        byte = np.ascontiguousarray(records[:, :, 0])
        bits = np.empty((height, width, light_count), dtype=np.uint8)
        for i in range(light_count):
            bits[:, :, i] = (byte >> np.uint8(i)) & np.uint8(1)
    else:
        bits = np.unpackbits(records[:, :, :used], axis=-1, count=light_count, bitorder="little")
    return bits.view(bool)


def as_words(bitmap: np.ndarray, width: int, layout: str, light_count: int) -> np.ndarray:
    """Views a ``paper32``/``words32`` bitmap as ``(H, W, words)`` uint32, the integers of seed 000 §3.2."""
    if layout not in ("paper32", "words32"):
        raise ValueError(f"layout '{layout}' is not word-based")
    bpp = bytes_per_pixel(layout, light_count)
    raw = np.ascontiguousarray(bitmap, dtype=np.uint8)
    return raw.reshape(-1, width, bpp).view("<u4")


def all_lit_row(width: int, light_count: int, layout: str) -> np.ndarray:
    """One bitmap row with every light unobstructed (the ``lit`` UDP repair, and a light-count check)."""
    return pack(np.ones((1, width, light_count), dtype=bool), layout)[0]
