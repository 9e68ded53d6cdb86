"""Texture images from the archives, decoded by OpenImageIO.

Lookup follows ioquake3's ``R_FindImageFile``: the name as given, then the same name with each known extension in
the renderer's order (``.tga``, ``.png``, ``.jpg``, ``.jpeg``). Images are kept as 8-bit sRGB RGBA with row 0 at
the top, which is where Quake III's texture coordinate t = 0 lies, so a Quake ``(s, t)`` pair is used directly
as the suite's ``(u, v)`` (the scene model stores row 0 at v = 0). Images wider or taller than
``max_size`` are box-filtered down by powers of two in linear light.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from suite.core.scene.q3.paks import PakFS

EXTENSIONS = (".tga", ".png", ".jpg", ".jpeg")


def candidates(name: str) -> list[str]:
    base, ext = os.path.splitext(name)
    if ext.lower() not in EXTENSIONS:
        base = name
    return ([name] if ext else []) + [base + e for e in EXTENSIONS if base + e != name]


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


_LUT = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)


def decode_srgb8(rgb8: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> float32 linear through a 256-entry table."""
    return _LUT[rgb8]


class TextureLoader:
    """Finds and decodes images in a :class:`PakFS`; remembers results (and misses) by name."""

    def __init__(self, fs: PakFS, max_size: int = 256):
        self.fs = fs
        self.max_size = int(max_size)
        self._cache: dict[str, np.ndarray | None] = {}
        self._average: dict[str, np.ndarray] = {}
        self._tmp = tempfile.TemporaryDirectory(prefix="splitbench-q3tex-")
        self.decode_errors: dict[str, str] = {}

    def close(self) -> None:
        self._tmp.cleanup()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def find(self, name: str) -> str | None:
        for c in candidates(name):
            if self.fs.find(c) is not None:
                return c
        return None

    def load(self, name: str) -> np.ndarray | None:
        """(H, W, 4) uint8 sRGB RGBA with row 0 at the top, or None if no image of that name decodes."""
        key = name.lower()
        if key not in self._cache:
            self._cache[key] = self._load(name)
        return self._cache[key]

    def _load(self, name: str) -> np.ndarray | None:
        path = self.find(name)
        if path is None:
            return None
        import OpenImageIO as oiio

        data = self.fs.read(path)
        # OpenImageIO's Python binding reads files, not memory: the member goes through a private temp file.
        tmp = os.path.join(self._tmp.name, "img" + os.path.splitext(path)[1].lower())
        with open(tmp, "wb") as fh:
            fh.write(data)
        inp = oiio.ImageInput.open(tmp)
        if inp is None:
            self.decode_errors[name] = oiio.geterror() or "cannot open"
            return None
        try:
            spec = inp.spec()
            pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.UINT8)
            if pixels is None or not hasattr(pixels, "shape"):
                self.decode_errors[name] = inp.geterror() or "cannot read"
                return None
        finally:
            inp.close()
        img = np.asarray(pixels, np.uint8).reshape(spec.height, spec.width, spec.nchannels)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        elif img.shape[2] == 2:  # grey + alpha
            img = np.concatenate([np.repeat(img[:, :, :1], 3, axis=2), img[:, :, 1:]], axis=2)
        if img.shape[2] == 3:
            img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=2)
        self._average[name.lower()] = average_color_srgb8(img)  # at full resolution, as q3map2 sums it
        return np.ascontiguousarray(self._shrink(img[:, :, :4]))

    def average_srgb8(self, name: str) -> np.ndarray | None:
        """Mean 8-bit RGB of the full-resolution image (what q3map2 averages for a light colour), or None."""
        if self.load(name) is None:
            return None
        return self._average[name.lower()]

    def _shrink(self, img: np.ndarray) -> np.ndarray:
        h, w = img.shape[:2]
        factor = 1
        while max(h, w) // factor > self.max_size and min(h, w) // factor >= 2:
            factor *= 2
        if factor == 1:
            return img
        h2, w2 = h // factor, w // factor
        crop = img[:h2 * factor, :w2 * factor]
        lin = decode_srgb8(crop[:, :, :3]).reshape(h2, factor, w2, factor, 3).mean(axis=(1, 3))
        alpha = crop[:, :, 3].reshape(h2, factor, w2, factor).astype(np.float32).mean(axis=(1, 3))
        rgb8 = np.rint(linear_to_srgb(lin) * 255.0).astype(np.uint8)
        return np.concatenate([rgb8, np.rint(alpha).astype(np.uint8)[:, :, None]], axis=2)


def average_color_srgb8(img: np.ndarray) -> np.ndarray:
    """Mean of the 8-bit RGB texels (what q3map2 sums for a light image), in [0, 255]."""
    return img[:, :, :3].reshape(-1, 3).astype(np.float64).mean(axis=0)
