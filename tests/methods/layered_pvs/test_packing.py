"""Packing of seed 002 (§4.1.3-§4.1.5, Algorithms 2 and 4.1): exact round trips, fragment order kept."""
import numpy as np
import pytest

from methods.layered_pvs import codecs, packing


def _layers(rng, L=4, h=16, w=24, empty_block=True):
    count = rng.integers(0, L + 1, (h, w))
    if empty_block:
        count[:8, :8] = 0
    valid = np.arange(L)[:, None, None] < count[None]
    depth = np.where(valid, np.cumsum(rng.random((L, h, w)), axis=0) + 3 * rng.random((h, w)), np.inf)
    colour = rng.integers(0, 256, (L, h, w, 3)).astype(np.uint8)
    return count, valid, depth.astype(np.float32), colour


@pytest.mark.parametrize("order", packing.ORDERS)
@pytest.mark.parametrize("full_layers", [0, 1, 2])
@pytest.mark.parametrize("relocate", [False, True])
def test01_pack_unpack_relocate_back_round_trips_exactly(order, full_layers, relocate):
    rng = np.random.default_rng(full_layers + 10 * relocate)
    count, valid, depth, colour = _layers(rng)
    slot_of = packing.relocate(depth, valid, 8) if relocate else packing.identity_slots(valid)
    slot_colour, occupied = packing.to_slots(colour, valid, slot_of)
    counts = np.maximum(packing.block_layer_counts(occupied, 8) - full_layers, 0)
    layout = packing.make_layout(counts, 24, 16, 8, full_layers, order)
    tex, mask = packing.pack(slot_colour, occupied, layout)
    assert tex.shape[0] == layout.texture_height
    # The mask goes through its lossless codec, 'any' pixels resolved by the codec.
    mask_bin = codecs.quadtree_decode(codecs.quadtree_encode(mask), mask.shape)
    sc, sm, _ = packing.unpack(tex, mask_bin, layout, 4)
    back, back_valid = packing.relocate_back(sc, sm, count)
    assert np.array_equal(back_valid, valid)
    assert np.array_equal(back[valid], colour[valid])


def test02_relocation_keeps_fragment_order_and_block_layer_counts():
    rng = np.random.default_rng(2)
    count, valid, depth, _ = _layers(rng, L=5, h=32, w=32, empty_block=False)
    slot_of = packing.relocate(depth, valid, 8)
    before = packing.block_layer_counts(valid, 8)
    _, occupied = packing.to_slots(np.zeros(valid.shape + (1,)), valid, slot_of)
    assert np.array_equal(packing.block_layer_counts(occupied, 8), before) or \
        (packing.block_layer_counts(occupied, 8) <= before).all()
    s = np.where(valid, slot_of, -1)
    # Fragment k+1 of a pixel sits in a later slot than fragment k: the order is kept.
    both = valid[1:] & valid[:-1]
    assert (s[1:][both] > s[:-1][both]).all()
    assert (slot_of[valid] >= np.nonzero(valid)[0]).all()     # fragments only move back
    assert (slot_of != packing.identity_slots(valid)).any()    # and some did move


def test03_relocation_moves_a_surface_continued_in_the_next_layer():
    # A floor at depth 10 whose left half is covered by a box at depth 5: the floor's visible right half is in
    # layer 0 and its left half in layer 1. Algorithm 2 moves the right half to layer 1 (depth continuity).
    L, h, w = 2, 8, 8
    valid = np.zeros((L, h, w), bool)
    depth = np.full((L, h, w), np.inf, np.float32)
    valid[0] = True
    depth[0, :, :4], depth[0, :, 4:] = 5.0, 10.0
    valid[1, :, :4] = True
    depth[1, :, :4] = 10.0
    slot_of = packing.relocate(depth, valid, 8)
    assert (slot_of[0, :, 4] == 1).all()      # the floor's column next to the box edge moved to slot 1


def test04_every_tile_empty_in_a_layer_packs_no_tile():
    valid = np.zeros((3, 16, 16), bool)
    valid[0] = True
    colour = np.full((3, 16, 16, 3), 9, np.uint8)
    slot_colour, occupied = packing.to_slots(colour, valid, packing.identity_slots(valid))
    counts = np.maximum(packing.block_layer_counts(occupied, 8) - 1, 0)
    layout = packing.make_layout(counts, 16, 16, 8, 1, "block")
    tex, mask = packing.pack(slot_colour, occupied, layout)
    assert layout.tiles == 0 and tex.shape == (16, 16, 3)
    assert (mask == 1).all()


def test05_algorithm_4_1_addresses_block_first_and_layer_first_tiles():
    counts = np.array([[2, 0], [1, 3]])
    for order in packing.ORDERS:
        lay = packing.make_layout(counts, 16, 16, 8, 1, order)
        tx, ty, stored = packing.slot_texel(lay, np.array([0, 8, 0, 8, 8]), np.array([0, 0, 8, 8, 8]),
                                            np.array([2, 1, 1, 3, 4]))
        assert stored.tolist() == [True, False, True, True, False]
        idx = (ty[stored] - 16) // 8 * 2 + tx[stored] // 8
        expected = {"block": [1, 2, 5], "layer": [3, 1, 5]}[order]
        assert idx.tolist() == expected


def test06_colour_filling_fills_every_empty_texel_of_a_nonempty_tile_only():
    tex = np.zeros((8, 16, 3), np.uint8)
    filled = np.zeros((8, 16), bool)
    tex[3, 3] = (200, 100, 50)
    filled[3, 3] = True
    out = packing.colour_fill(tex, filled, 8)
    assert (out[:, :8] == (200, 100, 50)).all()     # the first tile takes its one colour everywhere
    assert (out[:, 8:] == 0).all()                  # the empty second tile stays as it was


@pytest.mark.parametrize("shape, rounds", [((40, 48), None), ((37, 29), None), ((40, 48), 2)])
def test07_compiled_colour_filling_gives_the_bits_of_the_numpy_rounds(shape, rounds):
    rng = np.random.default_rng(5)
    tex = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    filled = rng.random(shape) < 0.08          # sparse: many rounds, some tiles with no fragment at all
    filled[:8, :8] = False
    tex[~filled] = 0
    got = packing.colour_fill(tex, filled, 8, rounds)
    ref = packing.colour_fill_reference(tex, filled, 8, rounds)
    assert got.dtype == ref.dtype and np.array_equal(got, ref)
    assert (got[:8, :8] == 0).all() and (got[~filled] > 0).any()


@pytest.mark.parametrize("order", packing.ORDERS)
@pytest.mark.parametrize("full_layers", [0, 1, 4])
def test08_compiled_packing_gives_the_texture_and_mask_of_the_numpy_gathers(order, full_layers):
    rng = np.random.default_rng(20 + full_layers)
    count, valid, depth, colour = _layers(rng, L=4, h=32, w=40)
    slot_colour, occupied = packing.to_slots(colour, valid, packing.relocate(depth, valid, 8))
    counts = np.maximum(packing.block_layer_counts(occupied, 8) - full_layers, 0)
    layout = packing.make_layout(counts, 40, 32, 8, full_layers, order)
    got, ref = packing.pack(slot_colour, occupied, layout), packing.pack_reference(slot_colour, occupied, layout)
    for a, b in zip(got, ref):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert set(np.unique(got[1])) <= {0, 1, codecs.ANY} and (got[1] == 1).sum() == valid.sum()
    # the client's lookup (Algorithm 4.1, compiled) reads what slot_texel addresses
    yy, xx = (a.ravel() for a in np.mgrid[0:32, 0:40])
    want = np.arange(xx.size) % 7 != 0
    for s in range(4):
        tx, ty, stored = packing.slot_texel(layout, xx, yy, np.full(xx.size, s))
        out = np.zeros((xx.size, 3), np.uint8)
        ok = packing.fetch(layout, got[0], xx, yy, np.full(xx.size, s), want, np.arange(xx.size)[::-1], out)
        assert np.array_equal(ok, stored & want)
        assert np.array_equal(out[::-1][ok], got[0][ty[ok], tx[ok]]) and not out[::-1][~ok].any()
    # a count that leaves out a slot holding fragments is refused, as by the reference
    if counts.any():
        short = np.where(counts > 0, counts - 1, 0)
        bad = packing.make_layout(short, 40, 32, 8, full_layers, order)
        for fn in (packing.pack, packing.pack_reference):
            with pytest.raises(ValueError, match="excludes it"):
                fn(slot_colour, occupied, bad)


@pytest.mark.parametrize("order", packing.ORDERS)
@pytest.mark.parametrize("full_layers", [0, 1, 2])
def test09_unpack_in_one_compiled_pass_equals_the_numpy_gathers(order, full_layers):
    """Every slot's colour, stored mask value ('any' pixels included, as packed and as the codec resolves them)
    and whether it is stored: the compiled pass gives the reference's arrays."""
    rng = np.random.default_rng(30 + full_layers)
    count, valid, depth, colour = _layers(rng)
    slot_colour, occupied = packing.to_slots(colour, valid, packing.relocate(depth, valid, 8))
    counts = np.maximum(packing.block_layer_counts(occupied, 8) - full_layers, 0)
    layout = packing.make_layout(counts, 24, 16, 8, full_layers, order)
    tex, mask = packing.pack(slot_colour, occupied, layout)
    assert (mask == codecs.ANY).any()
    for m in (mask, codecs.quadtree_decode(codecs.quadtree_encode(mask), mask.shape)):
        got, want = packing.unpack(tex, m, layout, 4), packing.unpack_reference(tex, m, layout, 4)
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(got, want))
        assert want[2].any() and not want[2].all()


def test10_compiled_relocation_back_equals_the_numpy_ranks():
    """The k-th set slot of a pixel goes to layer k while k is below the client's count: the compiled pass gives the
    reference's colours and validity, with counts below, at and above the set slots and a mask with gaps."""
    rng = np.random.default_rng(41)
    L, h, w = 4, 16, 24
    slot_mask = (rng.random((L, h, w)) < 0.6).astype(np.uint8)
    slot_colour = rng.integers(0, 256, (L, h, w, 3), dtype=np.uint8)
    counts = rng.integers(0, L + 2, (h, w))
    got = packing.relocate_back(slot_colour, slot_mask, counts)
    want = packing.relocate_back_reference(slot_colour, slot_mask, counts)
    assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(got, want))
    assert want[1].any() and not want[1].all()
    ranks_past = slot_mask.copy()
    ranks_past[:, 0, 0] = 2                       # mask values of 2 rank the fourth slot past the last layer
    counts[0, 0] = 99
    with pytest.raises(IndexError):
        packing.relocate_back_reference(slot_colour, ranks_past, counts)
    with pytest.raises(IndexError):
        packing.relocate_back(slot_colour, ranks_past, counts)


@pytest.mark.parametrize("trailing", [(3,), (1,), ()])
def test11_compiled_scatter_into_slots_equals_the_numpy_fancy_indexing(trailing):
    rng = np.random.default_rng(len(trailing))
    _, valid, depth, _ = _layers(rng, L=5, h=32, w=24)
    slot_of = packing.relocate(depth, valid, 8)
    values = rng.random(valid.shape + trailing).astype(np.float32)
    got, got_occ = packing.to_slots(values, valid, slot_of)
    want, want_occ = packing.to_slots_reference(values, valid, slot_of)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got, want) and np.array_equal(got_occ, want_occ)
    assert not np.array_equal(got_occ, valid)       # relocation moved fragments to other slots


def test12_a_fragment_in_a_tile_the_block_counts_exclude_is_an_error_naming_its_slot():
    rng = np.random.default_rng(12)
    _, valid, depth, colour = _layers(rng, L=4, empty_block=False)
    slot_colour, occupied = packing.to_slots(colour, valid, packing.identity_slots(valid))
    counts = np.maximum(packing.block_layer_counts(occupied, 8) - 1, 0)
    by, bx = np.unravel_index(np.argmax(counts), counts.shape)
    short = counts.copy()
    short[by, bx] -= 1                      # the block's last tiled slot is left out
    layout = packing.make_layout(short, 24, 16, 8, 1, "block")
    with pytest.raises(ValueError, match=f"slot {int(counts[by, bx])} holds fragments"):
        packing.pack(slot_colour, occupied, layout)
    with pytest.raises(ValueError, match="holds fragments"):
        packing.pack_reference(slot_colour, occupied, layout)
