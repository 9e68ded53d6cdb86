"""The visibility bitmap's layouts, sizes and exact bit order (seed 000 §3.2, §4.3.1, §6.2)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from methods.visibility_bitmap import bitmap as bm
from suite.errors import UserError

HARD_LIGHT_COUNTS = [0, 1, 32, 33, 64]


def test01_paper32_frame_at_1080p_is_8294400_bytes_for_any_count_up_to_32():
    # seed 000 §5.2: 1920 * 1080 * 4 bytes per pixel.
    for lights in (0, 1, 3, 32):
        assert bm.bitmap_nbytes(1920, 1080, lights, "paper32") == 8_294_400


def test02_paper32_refuses_33_lights_with_a_user_error():
    with pytest.raises(UserError, match="at most 32 lights"):
        bm.bytes_per_pixel("paper32", 33)


@pytest.mark.parametrize("lights,words32,packed8", [(0, 0, 0), (1, 4, 1), (8, 4, 1), (9, 4, 2), (32, 4, 4),
                                                    (33, 8, 5), (64, 8, 8), (65, 12, 9)])
def test03_record_size_follows_the_light_count(lights, words32, packed8):
    assert bm.bytes_per_pixel("words32", lights) == words32
    assert bm.bytes_per_pixel("packed8", lights) == packed8


@pytest.mark.parametrize("lights", [n for n in HARD_LIGHT_COUNTS if n > 0])
def test04_light_i_alone_sets_word_i_div_32_bit_i_mod_32(lights):
    # seed 000 Alg. 3B-2 step 4.2.2: v |= 1 << i; words32 extends it word by word (§6.2).
    layouts = ["words32"] + (["paper32"] if lights <= 32 else [])
    for layout in layouts:
        for i in sorted({0, lights // 2, lights - 1, min(31, lights - 1), min(32, lights - 1)}):
            vis = np.zeros((1, 2, lights), bool)
            vis[0, 1, i] = True
            words = bm.as_words(bm.pack(vis, layout), 2, layout, lights)
            expected = np.zeros(words.shape[-1], np.uint32)
            expected[i // 32] = np.uint32(1) << np.uint32(i % 32)
            assert np.array_equal(words[0, 1], expected), (layout, i)
            assert not words[0, 0].any()


def test05_paper_example_mask_0110_means_lights_1_and_2_unobstructed():
    # seed 000 §3.2: '...0110' → k_shadow,1 = k_shadow,2 = 1, k_shadow,0 = k_shadow,3 = 0.
    raw = np.frombuffer(np.array([0b0110], "<u4").tobytes(), np.uint8).reshape(1, 4)
    assert bm.unpack(raw, 1, 4, "paper32")[0, 0].tolist() == [False, True, True, False]


@pytest.mark.parametrize("layout,lights", [(layout, n) for layout in bm.LAYOUTS for n in HARD_LIGHT_COUNTS + [3, 8, 9]
                                           if not (layout == "paper32" and n > 32)])
def test06_pack_then_unpack_gives_the_visibility_back(layout, lights):
    vis = np.random.default_rng(lights).random((5, 7, lights)) < 0.5
    raw = bm.pack(vis, layout)
    assert raw.shape == (5, 7 * bm.bytes_per_pixel(layout, lights))
    assert np.array_equal(bm.unpack(raw, 7, lights, layout), vis)


@pytest.mark.parametrize("lights", [1, 3, 32, 33, 64])
def test07_packed8_record_is_the_little_endian_prefix_of_the_word_record(lights):
    vis = np.random.default_rng(7).random((3, 4, lights)) < 0.5
    words = bm.pack(vis, "words32").reshape(3, 4, -1)
    packed = bm.pack(vis, "packed8").reshape(3, 4, -1)
    nb = packed.shape[-1]
    assert np.array_equal(words[..., :nb], packed)
    assert not words[..., nb:].any()


def test08_row_r_of_the_image_is_row_r_of_the_bitmap():
    vis = np.zeros((4, 3, 2), bool)
    vis[2, :, 1] = True
    raw = bm.pack(vis, "paper32")
    assert raw[2].any() and not np.delete(raw, 2, axis=0).any()


def test09_unknown_layout_is_a_user_error():
    with pytest.raises(UserError, match="unknown visibility bitmap layout"):
        bm.pack(np.zeros((1, 1, 1), bool), "rgba8")


def test10_all_lit_row_unpacks_to_every_light_visible():
    for layout, lights in (("paper32", 3), ("words32", 33), ("packed8", 9)):
        row = bm.all_lit_row(5, lights, layout)
        assert bm.unpack(row[None], 5, lights, layout).all()


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 4), w=st.integers(1, 9), lights=st.integers(0, 70), seed=st.integers(0, 2**16))
def test11_roundtrip_holds_for_any_shape_and_light_count(h, w, lights, seed):
    vis = np.random.default_rng(seed).random((h, w, lights)) < 0.5
    for layout in ("words32", "packed8"):
        assert np.array_equal(bm.unpack(bm.pack(vis, layout), w, lights, layout), vis)
