"""Codecs for the visibility bitmap on the wire.

A codec is named by a spec ``[delta+][bitplane+]BASE[:LEVEL]``:

``BASE``
    ``none`` (the raw bitmap, seed 000's ``no-compression`` mode), ``lzo`` (LZO1X-1, the codec seed 000 §4.5.3
    used; available only when python-lzo is installed), ``lz4`` (LZ4 block), ``zstd`` (Zstandard, level 3 unless
    ``zstd:LEVEL``), ``h264`` (lossless H.264 through PyAV's libx264, the codec seed 000 §5.2 and §6.3 recommend).
``bitplane+``
    Regroups the bits so that each bit position of the per-pixel record becomes its own plane (an image of
    1 bit per pixel). Unused light bits become runs of zeros, and each light's shadow becomes a binary image,
    which general-purpose codecs compress far better than interleaved masks.
``delta+``
    Temporal delta: XOR with the previous frame's bitmap of the same slice (seed 000 §4.5.3: "it does not make
    use of previous frames and sending deltas, which is used by H.264"). A keyframe carries no delta.

Every codec here is lossless and a test proves it on bitmaps with 0–64 lights. Codecs with temporal state
(``delta+`` and ``h264``, which uses P-frames) need the decoder to hold the previous frame of the same slice: a
lost slice leaves the decoder without a reference until the next keyframe (:class:`SliceDecoder` reports this
as ``None``). H.264 maps bytes to luma samples of a ``gray`` (4:0:0) frame at ``qp=0``, which x264 codes
losslessly (High 4:4:4 Predictive, transform bypass); without ``bitplane+`` each byte of the pixel record
becomes its own plane of the image so that neighbouring samples are neighbouring pixels.

No lossy codec is offered: one flipped bit turns a shadow into light, so a lossy mode would have to be measured
for shading error (design rule); see the report notes in ``method.py``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from suite.errors import UserError

BASES = ("none", "lzo", "lz4", "zstd", "h264")
TRANSFORMS = ("delta", "bitplane")

#: Base codec ids on the wire (see :mod:`.wire`). Never renumber: stored payloads would decode wrongly.
BASE_IDS = {"none": 0, "lzo": 1, "lz4": 2, "zstd": 3, "h264": 4}
BASE_NAMES = {v: k for k, v in BASE_IDS.items()}

#: Transform flags on the wire (bits of the header's flags byte; bit 0 is the keyframe flag).
FLAG_KEYFRAME = 0x01
FLAG_BITPLANE = 0x02
FLAG_DELTA = 0x04

DEFAULT_ZSTD_LEVEL = 3


def unavailable_reason(base: str) -> str | None:
    """Why ``base`` cannot run here, or None when it can."""
    if base == "lzo":
        try:
            import lzo  # noqa: F401
        except ImportError:
            return "python-lzo is not installed (pip install 'splitbench[lzo]'; needs liblzo2-dev)"
    if base == "h264":
        try:
            import av
        except ImportError:
            return "PyAV is not installed"
        if "libx264" not in av.codecs_available:
            return "PyAV's FFmpeg was built without libx264"
    return None


@dataclass(frozen=True)
class CodecSpec:
    """A parsed codec spec; ``str()`` gives the canonical name (``delta+bitplane+zstd:3``)."""

    base: str
    bitplane: bool = False
    delta: bool = False
    level: int | None = None

    def __str__(self) -> str:
        parts = (["delta"] if self.delta else []) + (["bitplane"] if self.bitplane else [])
        base = self.base if self.level is None else f"{self.base}:{self.level}"
        return "+".join(parts + [base])

    @property
    def temporal(self) -> bool:
        """True when decoding a frame needs the previous frame of the same slice."""
        return self.delta or self.base == "h264"

    @property
    def lossless(self) -> bool:
        return True

    @property
    def flags(self) -> int:
        return (FLAG_BITPLANE if self.bitplane else 0) | (FLAG_DELTA if self.delta else 0)


def parse(spec: str) -> CodecSpec:
    """Parses ``[delta+][bitplane+]BASE[:LEVEL]``; raises :class:`UserError` on unknown or unavailable codecs."""
    text = str(spec).strip().lower()
    parts = [p for p in text.split("+") if p]
    if not parts:
        raise UserError("empty codec name (choose from none, lzo, lz4, zstd, h264, with optional delta+/bitplane+)")
    base_text, transforms = parts[-1], parts[:-1]
    base, _, level_text = base_text.partition(":")
    if base not in BASES:
        raise UserError(f"unknown codec '{spec}' (base codecs: {', '.join(BASES)}; transforms: delta+, bitplane+)")
    for t in transforms:
        if t not in TRANSFORMS:
            raise UserError(f"unknown codec transform '{t}' in '{spec}' (choose from delta+, bitplane+)")
    if len(set(transforms)) != len(transforms):
        raise UserError(f"codec transform repeated in '{spec}'")
    level = None
    if level_text:
        if base != "zstd":
            raise UserError(f"codec '{base}' takes no level (only zstd:LEVEL does)")
        try:
            level = int(level_text)
        except ValueError:
            raise UserError(f"zstd level must be an integer, got '{level_text}'") from None
        if not 1 <= level <= 22:
            raise UserError(f"zstd level must be within 1..22, got {level}")
    reason = unavailable_reason(base)
    if reason:
        raise UserError(f"codec '{base}' is unavailable: {reason}")
    return CodecSpec(base=base, bitplane="bitplane" in transforms, delta="delta" in transforms, level=level)


def from_wire(base_id: int, flags: int) -> CodecSpec:
    """The spec a received header describes (level is not needed to decode)."""
    if base_id not in BASE_NAMES:
        raise ValueError(f"unknown codec id {base_id}")
    return CodecSpec(base=BASE_NAMES[base_id], bitplane=bool(flags & FLAG_BITPLANE), delta=bool(flags & FLAG_DELTA))


# --- transforms: pure functions on (rows, row_bytes) uint8 arrays --------------------------------------------


def bitplane_forward(raw: np.ndarray, bytes_per_pixel: int) -> np.ndarray:
    """``(rows, W * bpp)`` → ``(8 * bpp * rows, ceil(W / 8))``: plane ``b`` holds bit ``b`` of every pixel record.

    Plane ``b`` is bit ``b % 8`` (from the LSB) of byte ``b // 8``, i.e. light ``b`` in every layout of
    :mod:`.bitmap`; within a plane, rows stay rows, pixels are packed LSB first.
    """
    rows = raw.shape[0]
    if bytes_per_pixel == 0 or raw.size == 0:
        return np.zeros((0, 0), dtype=np.uint8)
    width = raw.shape[1] // bytes_per_pixel
    byte_planes = byteplanes_forward(raw, bytes_per_pixel).reshape(bytes_per_pixel, rows, width)
    out = np.zeros((8 * bytes_per_pixel, rows, -(-width // 8)), dtype=np.uint8)
    # One pass per plane with packbits along the long pixel axis: much faster than unpacking every record.
    for k in range(bytes_per_pixel):
        if not byte_planes[k].any():
            continue  # bytes of unused lights (paper32 with few lights) stay all-zero planes
        for bit in range(8):
            out[8 * k + bit] = np.packbits((byte_planes[k] >> np.uint8(bit)) & np.uint8(1), axis=-1,
                                           bitorder="little")
    return out.reshape(8 * bytes_per_pixel * rows, -1)


def bitplane_inverse(planes: np.ndarray, rows: int, width: int, bytes_per_pixel: int) -> np.ndarray:
    if bytes_per_pixel == 0 or rows == 0 or width == 0:
        return np.zeros((rows, width * bytes_per_pixel), dtype=np.uint8)
    packed = planes.reshape(8 * bytes_per_pixel, rows, -1)
    byte_planes = np.zeros((bytes_per_pixel, rows, width), dtype=np.uint8)
    for b in range(8 * bytes_per_pixel):
        if not packed[b].any():
            continue  # unused light bits: an all-zero plane adds nothing
        bits = np.unpackbits(packed[b], axis=-1, count=width, bitorder="little")
        byte_planes[b // 8] |= bits << np.uint8(b % 8)
    return byteplanes_inverse(byte_planes, rows, width, bytes_per_pixel)


def byteplanes_forward(raw: np.ndarray, bytes_per_pixel: int) -> np.ndarray:
    """``(rows, W * bpp)`` → ``(bpp * rows, W)``: byte ``k`` of every pixel record as its own image (for H.264)."""
    rows = raw.shape[0]
    if bytes_per_pixel == 0 or raw.size == 0:
        return np.zeros((0, 0), dtype=np.uint8)
    width = raw.shape[1] // bytes_per_pixel
    return np.ascontiguousarray(raw.reshape(rows, width, bytes_per_pixel).transpose(2, 0, 1)).reshape(-1, width)


def byteplanes_inverse(planes: np.ndarray, rows: int, width: int, bytes_per_pixel: int) -> np.ndarray:
    if bytes_per_pixel == 0 or rows == 0 or width == 0:
        return np.zeros((rows, width * bytes_per_pixel), dtype=np.uint8)
    planes = planes.reshape(bytes_per_pixel, rows, width)
    return np.ascontiguousarray(planes.transpose(1, 2, 0)).reshape(rows, width * bytes_per_pixel)


# --- base codecs ------------------------------------------------------------------------------------------------


class _H264Stream:
    """One lossless libx264 encoder or h264 decoder holding the P-frame reference of one slice."""

    def __init__(self, image_shape: tuple[int, int], encoder: bool):
        import av

        self.height, self.width = image_shape
        # x264 needs even frame sizes; the padding is zeros and is cropped after decoding.
        self.padded = (self.height + (self.height & 1), self.width + (self.width & 1))
        if encoder:
            ctx = av.CodecContext.create("libx264", "w")
            ctx.width, ctx.height = self.padded[1], self.padded[0]
            ctx.pix_fmt = "gray"
            # qp=0 is x264's lossless mode; zerolatency + no B-frames give one packet per frame, no lookahead;
            # repeat-headers lets a fresh decoder start at any keyframe (needed after a lost UDP slice).
            ctx.options = {
                "qp": "0",
                "preset": "ultrafast",
                "tune": "zerolatency",
                "bframes": "0",
                "x264-params": "repeat-headers=1:keyint=100000:scenecut=0",
            }
            # One thread: x264's bitstream depends on its thread count, and bytes must not vary between machines.
            ctx.thread_count = 1
            ctx.open()
        else:
            ctx = av.CodecContext.create("h264", "r")
            ctx.thread_count = 1
        self.ctx = ctx

    def encode(self, image: np.ndarray, keyframe: bool) -> bytes:
        import av
        from av.video.frame import PictureType

        padded = np.zeros(self.padded, dtype=np.uint8)
        padded[: self.height, : self.width] = image
        frame = av.VideoFrame.from_ndarray(padded, format="gray")
        frame.pict_type = PictureType.I if keyframe else PictureType.NONE
        packets = self.ctx.encode(frame)
        return b"".join(bytes(p) for p in packets)

    def decode(self, data: bytes) -> np.ndarray:
        import av

        # One encoder call yields one packet (zerolatency, no B-frames), so one packet decodes to one frame.
        frames = self.ctx.decode(av.Packet(bytes(data)))
        if len(frames) != 1:
            raise ValueError(f"h264 payload decoded to {len(frames)} frames, expected 1")
        plane = frames[0].planes[0]
        # A gray stream decodes as yuv420p with neutral chroma; the luma plane holds the samples bit-exactly.
        luma = np.frombuffer(plane, dtype=np.uint8).reshape(-1, plane.line_size)
        return np.ascontiguousarray(luma[: self.height, : self.width])


def _compress(spec: CodecSpec, data: bytes) -> bytes:
    if spec.base == "none":
        return data
    if spec.base == "lz4":
        import lz4.block

        return lz4.block.compress(data, store_size=True)
    if spec.base == "zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=spec.level or DEFAULT_ZSTD_LEVEL).compress(data)
    if spec.base == "lzo":
        import lzo

        # Level 1 = LZO1X-1, the fast variant of the header-only miniLZO that seed 000 §4.5.3 used.
        return lzo.compress(data, 1)
    raise ValueError(spec.base)


def _decompress(spec: CodecSpec, data: bytes, raw_bytes: int) -> bytes:
    if spec.base == "none":
        out = data  # a memoryview of the message: no copy
    elif spec.base == "lz4":
        import lz4.block

        out = lz4.block.decompress(data)
    elif spec.base == "zstd":
        import zstandard

        out = zstandard.ZstdDecompressor().decompress(data, max_output_size=raw_bytes)
    elif spec.base == "lzo":
        import lzo

        out = lzo.decompress(bytes(data))
    else:
        raise ValueError(spec.base)
    if len(out) != raw_bytes:
        raise ValueError(f"decoded {len(out)} bytes, expected {raw_bytes}")
    return out


# --- stateful slice encoder / decoder ------------------------------------------------------------------------


#: Tallest H.264 frame we build; taller plane stacks are folded into side-by-side columns of planes, because
#: x264 refuses frames above 16,384 rows or columns (bit-planes of 64 lights at 360 rows would be 23,040 tall).
H264_MAX_HEIGHT = 4096
H264_MAX_WIDTH = 16384


def _tile_grid(n_planes: int, rows: int, cols: int) -> tuple[int, int]:
    tiles_x = min(max(-(-n_planes * rows // H264_MAX_HEIGHT), 1), n_planes)
    tiles_y = -(-n_planes // tiles_x)
    if tiles_x * cols > H264_MAX_WIDTH or tiles_y * rows > H264_MAX_WIDTH:
        raise UserError(f"bitmap too large for one H.264 frame ({n_planes} planes of {rows}x{cols}); "
                        "use UDP slices or another codec")
    return tiles_y, tiles_x


def tile_planes(stack: np.ndarray, n_planes: int) -> np.ndarray:
    """``(P * rows, cols)`` plane stack → one image of ``tiles_y × tiles_x`` planes (zero planes pad the grid)."""
    rows, cols = stack.shape[0] // n_planes, stack.shape[1]
    ty, tx = _tile_grid(n_planes, rows, cols)
    grid = np.zeros((ty * tx, rows, cols), dtype=np.uint8)
    grid[:n_planes] = stack.reshape(n_planes, rows, cols)
    return np.ascontiguousarray(grid.reshape(ty, tx, rows, cols).transpose(0, 2, 1, 3)).reshape(ty * rows, tx * cols)


def untile_planes(image: np.ndarray, n_planes: int, rows: int, cols: int) -> np.ndarray:
    ty, tx = _tile_grid(n_planes, rows, cols)
    grid = image.reshape(ty, rows, tx, cols).transpose(0, 2, 1, 3).reshape(ty * tx, rows, cols)
    return np.ascontiguousarray(grid[:n_planes]).reshape(n_planes * rows, cols)


class _SliceCodec:
    """What an encoder and a decoder of one slice share: its shape, codec and temporal reference."""

    def __init__(self, spec: CodecSpec, rows: int, width: int, bytes_per_pixel: int):
        self.spec, self.rows, self.width, self.bpp = spec, rows, width, bytes_per_pixel
        self._previous: np.ndarray | None = None
        self._h264: _H264Stream | None = None

    def _planes(self) -> int:
        """Planes in the H.264 image: one per bit (bit-plane transform) or per byte of the pixel record."""
        return 8 * self.bpp if self.spec.bitplane else self.bpp


class SliceEncoder(_SliceCodec):
    """Encodes successive frames of one slice (``rows`` × ``width`` pixels of ``bytes_per_pixel``)."""

    def _image(self, raw: np.ndarray) -> np.ndarray:
        if self.spec.bitplane:
            return bitplane_forward(raw, self.bpp)
        if self.spec.base == "h264":
            return byteplanes_forward(raw, self.bpp)
        return raw

    def encode(self, raw: np.ndarray, keyframe: bool) -> bytes:
        """``raw``: ``(rows, width * bpp)`` uint8. A keyframe (or the first frame) carries no temporal reference."""
        raw = np.ascontiguousarray(raw, dtype=np.uint8)
        if raw.shape != (self.rows, self.width * self.bpp):
            raise ValueError(f"slice shape {raw.shape} != {(self.rows, self.width * self.bpp)}")
        keyframe = keyframe or self._previous is None
        work = raw if (keyframe or not self.spec.delta) else np.bitwise_xor(raw, self._previous)
        self._previous = raw.copy()
        if raw.size == 0:
            return b""
        image = self._image(work)
        if self.spec.base == "h264":
            image = tile_planes(image, self._planes())
            if self._h264 is None:
                self._h264 = _H264Stream(image.shape, encoder=True)
            return self._h264.encode(image, keyframe)
        return _compress(self.spec, image.tobytes())


class SliceDecoder(_SliceCodec):
    """Decodes what a :class:`SliceEncoder` produced; holds the temporal reference of its slice."""

    def lose(self) -> None:
        """The slice of this frame never arrived: a temporal codec has no reference until the next keyframe."""
        self._previous = None
        self._h264 = None

    def decode(self, data: bytes, keyframe: bool) -> np.ndarray | None:
        """Returns ``(rows, width * bpp)`` uint8, or None when a temporal codec lacks its reference.

        Raises ValueError when the payload does not decode (the caller marks the slice bad).
        """
        if self.spec.temporal and not keyframe and self._previous is None:
            return None
        raw_bytes = self.rows * self.width * self.bpp
        if raw_bytes == 0:
            image_raw = np.zeros((self.rows, 0), dtype=np.uint8)
        else:
            if self.spec.base == "h264":
                n_planes = self._planes()
                cols = -(-self.width // 8) if self.spec.bitplane else self.width
                ty, tx = _tile_grid(n_planes, self.rows, cols)
                if keyframe or self._h264 is None:
                    self._h264 = _H264Stream((ty * self.rows, tx * cols), encoder=False)
                image = untile_planes(self._h264.decode(data), n_planes, self.rows, cols)
            else:
                image_bytes = (
                    8 * self.bpp * self.rows * (-(-self.width // 8)) if self.spec.bitplane else raw_bytes
                )
                image = np.frombuffer(_decompress(self.spec, data, image_bytes), dtype=np.uint8)
            if self.spec.bitplane:
                image_raw = bitplane_inverse(image, self.rows, self.width, self.bpp)
            elif self.spec.base == "h264":
                image_raw = byteplanes_inverse(image, self.rows, self.width, self.bpp)
            else:
                image_raw = image.reshape(self.rows, self.width * self.bpp)
        if self.spec.delta and not keyframe:
            image_raw = np.bitwise_xor(image_raw, self._previous)
        self._previous = np.array(image_raw, dtype=np.uint8, copy=True)
        return self._previous.copy()


# --- measurement ----------------------------------------------------------------------------------------------


@dataclass
class CodecMeasurement:
    codec: str
    available: bool
    reason: str | None = None
    raw_bytes: int = 0
    encoded_bytes: int = 0
    encode_ms: float = float("nan")
    decode_ms: float = float("nan")
    bit_exact: bool | None = None

    @property
    def ratio(self) -> float:
        """Raw bytes over encoded bytes (higher is better)."""
        return self.raw_bytes / self.encoded_bytes if self.encoded_bytes else float("inf")

    def as_dict(self) -> dict:
        return {
            "codec": self.codec, "available": self.available, "reason": self.reason,
            "raw_bytes": self.raw_bytes, "encoded_bytes": self.encoded_bytes, "ratio": self.ratio,
            "encode_ms": self.encode_ms, "decode_ms": self.decode_ms, "bit_exact": self.bit_exact,
        }


def measure(spec_text: str, frames: list[np.ndarray], width: int, bytes_per_pixel: int,
            keyframe_interval: int = 0) -> CodecMeasurement:
    """Encodes and decodes a sequence of whole-frame bitmaps; totals bytes, mean ms per frame, bit-exactness.

    ``frames``: ``(H, W * bpp)`` uint8 arrays of one camera path, in order (temporal codecs use the order).
    ``keyframe_interval`` 0 means only the first frame is a keyframe. Wall times are for the report's codec
    table; they are measured on this machine and vary between runs.
    """
    base = spec_text.split("+")[-1].split(":")[0]
    reason = unavailable_reason(base)
    if reason:
        return CodecMeasurement(codec=spec_text, available=False, reason=reason)
    spec = parse(spec_text)
    rows = frames[0].shape[0]
    enc = SliceEncoder(spec, rows, width, bytes_per_pixel)
    dec = SliceDecoder(spec, rows, width, bytes_per_pixel)
    m = CodecMeasurement(codec=str(spec), available=True, bit_exact=True)
    enc_s = dec_s = 0.0
    for i, raw in enumerate(frames):
        key = i == 0 or (keyframe_interval > 0 and i % keyframe_interval == 0)
        t0 = time.perf_counter()
        data = enc.encode(raw, key)
        t1 = time.perf_counter()
        out = dec.decode(data, key)
        t2 = time.perf_counter()
        enc_s += t1 - t0
        dec_s += t2 - t1
        m.raw_bytes += raw.nbytes
        m.encoded_bytes += len(data)
        m.bit_exact = bool(m.bit_exact and out is not None and np.array_equal(out, raw))
    m.encode_ms = 1e3 * enc_s / len(frames)
    m.decode_ms = 1e3 * dec_s / len(frames)
    return m
