"""Wire codecs: every one is bit-exact, transforms are invertible, unavailable codecs are reported."""
import numpy as np
import pytest

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import codecs
from suite.errors import UserError

ALL_SPECS = ["none", "lzo", "lz4", "zstd", "zstd:9", "bitplane+lz4", "bitplane+zstd", "delta+lz4",
             "delta+bitplane+zstd", "h264", "bitplane+h264", "delta+h264"]


def available(spec):
    reason = codecs.unavailable_reason(spec.split("+")[-1].split(":")[0])
    if reason:
        pytest.skip(reason)
    return spec


def moving_shadow_frames(h, w, lights, n, layout):
    """A disc's shadow per light, moving a pixel per frame: realistic spatial and temporal coherence."""
    yy, xx = np.mgrid[:h, :w]
    frames = []
    for t in range(n):
        vis = np.stack([(xx - (w * (l + 1)) // (lights + 1) - t) ** 2 + (yy - h // 2) ** 2 > (h // 3) ** 2
                        for l in range(lights)], axis=-1) if lights else np.zeros((h, w, 0), bool)
        frames.append(bm.pack(vis, layout))
    return frames


@pytest.mark.parametrize("spec", ALL_SPECS)
@pytest.mark.parametrize("layout,lights", [("paper32", 0), ("paper32", 3), ("words32", 33), ("packed8", 64),
                                           ("words32", 0)])
def test01_every_codec_decodes_bit_exactly(spec, layout, lights):
    available(spec)
    frames = moving_shadow_frames(18, 22, lights, 4, layout)
    m = codecs.measure(spec, frames, 22, bm.bytes_per_pixel(layout, lights), keyframe_interval=3)
    assert m.available and m.bit_exact, m.as_dict()


@pytest.mark.parametrize("spec", ["h264", "bitplane+h264", "lz4", "delta+zstd"])
def test02_codecs_are_bit_exact_on_incompressible_random_bytes(spec):
    # Random bytes are H.264's worst case: any quantisation at all would show here.
    available(spec)
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 256, (13, 9 * 4), dtype=np.uint8) for _ in range(3)]
    assert codecs.measure(spec, frames, 9, 4).bit_exact


def test03_bitplane_plane_b_is_the_image_of_light_b():
    vis = np.random.default_rng(3).random((4, 10, 5)) < 0.5
    planes = codecs.bitplane_forward(bm.pack(vis, "paper32"), 4).reshape(32, 4, -1)
    for light in range(5):
        bits = np.unpackbits(planes[light], axis=-1, count=10, bitorder="little").astype(bool)
        assert np.array_equal(bits, vis[..., light])
    assert not planes[5:].any()  # unused bits of the 32-bit word are all-zero planes


@pytest.mark.parametrize("bpp,width", [(1, 1), (1, 9), (4, 7), (8, 16)])
def test04_bitplane_and_byteplane_transforms_invert(bpp, width):
    raw = np.random.default_rng(bpp).integers(0, 256, (3, width * bpp), dtype=np.uint8)
    assert np.array_equal(codecs.bitplane_inverse(codecs.bitplane_forward(raw, bpp), 3, width, bpp), raw)
    assert np.array_equal(codecs.byteplanes_inverse(codecs.byteplanes_forward(raw, bpp), 3, width, bpp), raw)


def test05_zstd_compresses_a_shadow_bitmap_more_than_tenfold():
    frames = moving_shadow_frames(90, 160, 3, 1, "paper32")
    assert codecs.measure("zstd", frames, 160, 4).ratio > 10


def test06_bitplane_beats_interleaved_masks_for_the_same_base_codec():
    frames = moving_shadow_frames(90, 160, 3, 2, "paper32")
    assert codecs.measure("bitplane+lz4", frames, 160, 4).ratio > codecs.measure("lz4", frames, 160, 4).ratio


@pytest.mark.parametrize("spec", ["delta+lz4", "h264"])
def test07_temporal_decoder_without_its_reference_returns_none_until_a_keyframe(spec):
    available(spec)
    frames = moving_shadow_frames(8, 8, 2, 3, "packed8")
    enc = codecs.SliceEncoder(codecs.parse(spec), 8, 8, 1)
    dec = codecs.SliceDecoder(codecs.parse(spec), 8, 8, 1)
    data = [enc.encode(frames[0], True), enc.encode(frames[1], False), enc.encode(frames[2], True)]
    assert np.array_equal(dec.decode(data[0], True), frames[0])
    dec.lose()
    assert dec.decode(data[1], False) is None
    assert np.array_equal(dec.decode(data[2], True), frames[2])


@pytest.mark.parametrize("spec,message", [("rle", "unknown codec"), ("foo+lz4", "unknown codec transform"),
                                          ("lz4:3", "takes no level"), ("zstd:99", "within 1..22"),
                                          ("delta+delta+lz4", "repeated")])
def test08_bad_codec_names_are_user_errors(spec, message):
    with pytest.raises(UserError, match=message):
        codecs.parse(spec)


def test09_spec_names_are_canonical():
    assert str(codecs.parse("BITPLANE+delta+zstd:5")) == "delta+bitplane+zstd:5"


def test10_missing_lzo_is_reported_as_unavailable_not_a_crash(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_lzo(name, *args, **kwargs):
        if name == "lzo":
            raise ImportError("no lzo")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_lzo)
    m = codecs.measure("lzo", moving_shadow_frames(4, 4, 1, 1, "paper32"), 4, 4)
    assert not m.available and "python-lzo" in m.reason
    with pytest.raises(UserError, match="unavailable"):
        codecs.parse("lzo")


def test11_wire_ids_round_trip_every_base_and_transform():
    for spec_text in ["none", "delta+bitplane+h264", "bitplane+lzo", "delta+zstd"]:
        spec = codecs.CodecSpec(*(lambda s: (s.split("+")[-1], "bitplane" in s, "delta" in s))(spec_text))
        assert codecs.from_wire(codecs.BASE_IDS[spec.base], spec.flags) == spec


def test12_h264_folds_tall_plane_stacks_and_stays_bit_exact():
    # 64 lights of bit-planes at 300 rows is 19,200 rows of planes: above x264's 16,384 limit unless folded.
    available("h264")
    frames = moving_shadow_frames(300, 40, 64, 2, "packed8")
    assert codecs.measure("bitplane+h264", frames, 40, 8).bit_exact


@pytest.mark.parametrize("n_planes,rows,cols", [(1, 5, 7), (32, 300, 10), (12, 1080, 1920)])
def test13_plane_tiling_inverts(n_planes, rows, cols):
    stack = np.random.default_rng(n_planes).integers(0, 256, (n_planes * rows, cols), dtype=np.uint8)
    image = codecs.tile_planes(stack, n_planes)
    assert image.shape[0] <= codecs.H264_MAX_HEIGHT or image.shape[0] == rows
    assert np.array_equal(codecs.untile_planes(image, n_planes, rows, cols), stack)


def test14_codec_table_reports_every_codec_with_its_bytes_and_exactness():
    from methods.visibility_bitmap.bench import codec_table

    vis = [np.random.default_rng(t).random((6, 10, 3)) < 0.5 for t in range(2)]
    rows = codec_table(vis, "packed8", ("none", "zstd", "delta+lz4"), repeats=1)
    assert [r["codec"] for r in rows] == ["none", "zstd", "delta+lz4"]
    assert rows[0]["bytes_per_frame"] == 60 and rows[0]["ratio"] == 1.0
    assert all(r["bit_exact"] for r in rows)
