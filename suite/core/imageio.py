"""Image files: OpenEXR for linear HDR images, PNG for viewing, both through OpenImageIO.

In memory an image is a numpy array of shape ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, C)``,
row 0 at the top. On disk:

- ``write_exr`` stores 32-bit float channels (lossless ZIP compression), so ``read_exr`` returns exactly the
  float32 values that were written. Channel names: ``Y`` (1), ``R G B`` (3), ``R G B A`` (4), ``R G B A`` plus
  numbered extras otherwise.
- ``write_png`` stores 8-bit sRGB after the display transform of :func:`suite.core.metrics.to_display`, so a PNG shows
  exactly what the metrics see.

Both writers are atomic (:func:`suite.fileio.atomic_target`): they write a temporary file in the destination's
directory and ``os.replace`` it over the destination, so an interrupted or failed write never leaves a
truncated image behind (the results store treats a present file as complete). OpenImageIO reports failure through return values instead of exceptions,
so every call's result is checked and its error text is raised.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from suite.errors import UserError

# The suite's one atomic writer (suite/fileio.py); suite.core.reference imports it from here too.
from suite.fileio import atomic_target


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _channel_names(num_channels: int) -> list[str]:
    if num_channels == 1:
        return ["Y"]
    if num_channels == 3:
        return ["R", "G", "B"]
    names = ["R", "G", "B", "A"][:num_channels]
    return names + [f"channel{i}" for i in range(len(names), num_channels)]


def _as_image_array(img, dtype, what: str) -> np.ndarray:
    """(H, W, C) C-contiguous copy in ``dtype``.

    OpenImageIO's ``write_image`` fails (returning False, with a half-written file) on non-contiguous
    buffers such as transposed Dr.Jit tensors, so the array handed to it is always made contiguous here.
    """
    arr = np.asarray(img)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[0] == 0 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise UserError(f"{what}: expected an image of shape (H, W) or (H, W, C), got {np.shape(img)}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
            or arr.dtype == np.bool_):
        raise UserError(f"{what}: expected a numeric image, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=dtype)


def _write_atomic(path, pixels: np.ndarray, attributes: dict[str, object]) -> None:
    oiio = _oiio()
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise UserError(f"cannot write image '{path}': directory '{directory}' does not exist")
    height, width, channels = pixels.shape
    fmt = oiio.FLOAT if pixels.dtype == np.float32 else oiio.UINT8
    spec = oiio.ImageSpec(width, height, channels, fmt)
    spec.channelnames = tuple(_channel_names(channels))
    for name, value in attributes.items():
        spec.attribute(name, value)
    # The temporary file keeps the destination's extension: OpenImageIO picks the format from it.
    with atomic_target(path, suffix=f".tmp{path.suffix}") as tmp_name:
        out = oiio.ImageOutput.create(tmp_name)
        if out is None:
            raise UserError(f"cannot write image '{path}': {oiio.geterror() or 'unsupported file type'}")
        try:
            if not out.open(tmp_name, spec):
                raise UserError(f"cannot write image '{path}': {out.geterror() or oiio.geterror()}")
            if not out.write_image(pixels):
                raise UserError(f"cannot write image '{path}': {out.geterror() or oiio.geterror()}")
        finally:
            closed = out.close()
        if not closed:
            raise UserError(f"cannot write image '{path}': {out.geterror() or oiio.geterror()}")


def write_exr(path, img) -> None:
    """Writes ``img`` (linear values, any float or integer dtype) as a float32 OpenEXR file, atomically."""
    pixels = _as_image_array(img, np.float32, f"image for '{path}'")
    _write_atomic(path, pixels, {"compression": "zip"})


def read_exr(path) -> np.ndarray:
    """Reads an image file (OpenEXR, or anything OpenImageIO reads) as a float32 C-contiguous array.

    Returns ``(H, W)`` for a one-channel file and ``(H, W, C)`` otherwise. A missing, unreadable or truncated
    file raises :class:`UserError` naming it.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise UserError(f"image file '{path}' does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"cannot read image '{path}': {oiio.geterror() or 'unknown format'}")
    try:
        pixels = inp.read_image(oiio.FLOAT)
        if pixels is None:
            raise UserError(f"cannot read image '{path}': {inp.geterror() or oiio.geterror()}")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    return np.ascontiguousarray(pixels)


def write_png(path, img_linear, exposure: float = 1.0) -> None:
    """Writes a linear HDR image as an 8-bit sRGB PNG through the metrics' display transform, atomically.

    ``exposure`` is the same linear multiplier as in :func:`suite.core.metrics.to_display`. One- and three-channel
    images are supported.
    """
    from suite.core.metrics import to_display

    arr = np.asarray(img_linear)
    if arr.ndim == 3 and arr.shape[2] not in (1, 3):
        raise UserError(f"image for '{path}': PNG output takes 1 or 3 channels, got {arr.shape[2]}")
    linear = _as_image_array(arr, np.float64, f"image for '{path}'")
    if not np.isfinite(linear).all():
        bad = int(np.size(linear) - np.count_nonzero(np.isfinite(linear)))
        raise UserError(f"image for '{path}' contains {bad} NaN/Inf values")
    display = to_display(linear, exposure=exposure)
    pixels = np.ascontiguousarray(np.rint(display * 255.0), dtype=np.uint8)
    _write_atomic(path, pixels, {"oiio:ColorSpace": "sRGB"})
