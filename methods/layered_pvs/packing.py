"""Packing of depth layers into one texture (seed 002 §4.1.3-§4.1.5, Fig. 4.4, Fig. 4.7, Algorithms 2 and 4.1).

Vocabulary of the thesis: a layer is divided into ``tile`` x ``tile`` tiles; a *block* is the column of tiles at one
position through all layers. A pixel's fragments occupy *slots* 0, 1, ... of its block (slot = layer after fragment
relocation). The first ``full_layers`` slots are stored whole, one under another at the top of the texture; the
other slots are stored as tiles, only for blocks that use them (``block counts`` = tiles per block), in
block-first or layer-first order, row-major in the texture (Fig. 4.7).

Arrays: slot arrays are (L, H, W) with H, W multiples of ``tile``; colours are uint8 RGB.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from methods.layered_pvs.codecs import ANY

ORDERS = ("block", "layer")


_compiled = None


def _passes() -> dict:
    """The compiled passes (numba, on first use; cached on disk). The texel helpers are compiled first: the passes
    that call them are typed against the compiled versions."""
    global _compiled, _texel, _tile_of
    if _compiled is None:
        j = numba.njit(cache=True, nogil=True)
        _tile_of = j(_tile_of)
        _texel = j(_texel)
        _compiled = {f.__name__: j(f) for f in (_relocate_pass, _pack_pass, _fetch_pass, _unpack_pass,
                                                _relocate_back_pass, _fill_pass, _to_slots_pass)}
    return _compiled


# ------------------------------------------------------------------------------------------ relocation

def _neighbour_views(a: np.ndarray, tile: int, fill):
    """The 4-neighbours of every pixel of (..., H, W) ``a`` restricted to the same block: (up, down, left, right),
    ``fill`` where the neighbour is outside the block."""
    h, w = a.shape[-2:]
    out = []
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        b = np.full_like(a, fill)
        ys = slice(max(dy, 0), h + min(dy, 0))
        yd = slice(max(-dy, 0), h + min(-dy, 0))
        xs = slice(max(dx, 0), w + min(dx, 0))
        xd = slice(max(-dx, 0), w + min(-dx, 0))
        b[..., yd, xd] = a[..., ys, xs]
        y = np.arange(h)
        x = np.arange(w)
        same_y = ((y + dy) // tile == y // tile) & (y + dy >= 0) & (y + dy < h)
        same_x = ((x + dx) // tile == x // tile) & (x + dx >= 0) & (x + dx < w)
        b[..., ~(same_y[:, None] & same_x[None, :])] = fill
        out.append(b)
    return out


def block_layer_counts(occupied: np.ndarray, tile: int) -> np.ndarray:
    """(By, Bx): layers a block uses = the largest number of slots any of its pixels needs."""
    L, h, w = occupied.shape
    used = np.where(occupied, np.arange(1, L + 1)[:, None, None], 0).max(axis=0)
    return used.reshape(h // tile, tile, w // tile, tile).max(axis=(1, 3))


def _relocate_pass(slot_frag, slot_depth, n_block, tile, max_rounds):
    """Algorithm 2 in place on slot arrays, block by block (see :func:`relocate`)."""
    L, h, w = slot_frag.shape
    moved = np.zeros((h, w), np.bool_)
    for by in range(h // tile):
        for bx in range(w // tile):
            nb = n_block[by, bx]
            y0, x0 = by * tile, bx * tile
            for k in range(nb - 1):
                for _ in range(max_rounds):
                    any_move = False
                    moved[y0:y0 + tile, x0:x0 + tile] = False
                    # Decide on the slot state at the start of the round (one GPU pass in the thesis).
                    for y in range(y0, y0 + tile):
                        for x in range(x0, x0 + tile):
                            if slot_frag[k, y, x] < 0:
                                continue
                            remaining = 0
                            for s in range(k, L):
                                if slot_frag[s, y, x] >= 0:
                                    remaining += 1
                            if remaining >= nb - k:
                                continue
                            d = slot_depth[k, y, x]
                            closer = False
                            for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                                yy, xx = y + dy, x + dx
                                if yy < y0 or yy >= y0 + tile or xx < x0 or xx >= x0 + tile:
                                    continue
                                nn = slot_depth[k + 1, yy, xx]
                                nc = slot_depth[k, yy, xx]
                                if np.isfinite(nn) and abs(d - nn) < abs(d - nc):
                                    closer = True
                            if closer:
                                moved[y, x] = True
                                any_move = True
                    if not any_move:
                        break
                    for y in range(y0, y0 + tile):
                        for x in range(x0, x0 + tile):
                            if not moved[y, x]:
                                continue
                            gap = k + 1
                            while slot_frag[gap, y, x] >= 0:
                                gap += 1
                            for s in range(gap, k, -1):
                                slot_frag[s, y, x] = slot_frag[s - 1, y, x]
                                slot_depth[s, y, x] = slot_depth[s - 1, y, x]
                            slot_frag[k, y, x] = -1
                    for y in range(y0, y0 + tile):
                        for x in range(x0, x0 + tile):
                            if not moved[y, x]:
                                continue
                            total = 0.0
                            cnt = 0
                            for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                                yy, xx = y + dy, x + dx
                                if yy < y0 or yy >= y0 + tile or xx < x0 or xx >= x0 + tile:
                                    continue
                                nn = slot_depth[k + 1, yy, xx]
                                if np.isfinite(nn):
                                    total += nn
                                    cnt += 1
                            slot_depth[k, y, x] = total / cnt if cnt > 0 else slot_depth[k + 1, y, x]


def relocate(depth: np.ndarray, valid: np.ndarray, tile: int, max_rounds: int = 64):
    """Fragment relocation (Algorithm 2, §4.1.4, §5.2) on peeled layers.

    ``depth``, ``valid``: (L, H, W), fragments of a pixel in layers 0..n-1 (depth order). Returns ``slot_of``
    (L, H, W) int: the slot of each pixel's k-th fragment (-1 where there is none). Per block and layer, round after
    round: fragments whose depth is closer to a 4-neighbour's fragment in the next slot than to that neighbour's
    fragment in the current slot move one slot back, with the run of fragments behind them, while the pixel still
    has space (fragments left < slots left in the block); the emptied slot takes the mean depth of the neighbours'
    next-slot fragments. Neighbours are taken inside the block only (one CUDA block per block in the thesis). The
    order of a pixel's fragments never changes; the block's layer count never grows.
    """
    L, h, w = valid.shape
    n_block = block_layer_counts(valid, tile).astype(np.int64)
    slot_frag = np.where(valid, np.arange(L)[:, None, None], -1).astype(np.int64)
    slot_depth = np.where(valid, depth, np.inf).astype(np.float64)
    _passes()["_relocate_pass"](slot_frag, slot_depth, n_block, int(tile), int(max_rounds))
    slot_of = np.full((L, h, w), -1, np.int64)
    s, y, x = np.nonzero(slot_frag >= 0)
    slot_of[slot_frag[s, y, x], y, x] = s
    return slot_of


def identity_slots(valid: np.ndarray) -> np.ndarray:
    """Slots without relocation: fragment k in slot k."""
    L = valid.shape[0]
    return np.where(valid, np.arange(L)[:, None, None], -1).astype(np.int64)


def to_slots(values: np.ndarray, valid: np.ndarray, slot_of: np.ndarray):
    """Scatters per-fragment ``values`` (L, H, W, ...) into slot order; returns (slot values, slot occupied). One
    compiled pass over the fragments (:func:`_to_slots_pass`)."""
    L, h, w = valid.shape
    flat = np.ascontiguousarray(values).reshape(L, h * w, -1)
    out = np.zeros_like(flat)
    occ = np.zeros((L, h * w), bool)
    _passes()["_to_slots_pass"](flat, np.ascontiguousarray(valid, np.bool_).reshape(L, -1),
                                np.ascontiguousarray(slot_of, np.int64).reshape(L, -1), out, occ)
    return out.reshape(np.shape(values)), occ.reshape(L, h, w)


def _to_slots_pass(values, valid, slot_of, out, occ):
    L, n, c = values.shape
    for k in range(L):
        for i in range(n):
            if valid[k, i]:
                s = slot_of[k, i]
                occ[s, i] = True
                for j in range(c):
                    out[s, i, j] = values[k, i, j]


def to_slots_reference(values: np.ndarray, valid: np.ndarray, slot_of: np.ndarray):
    """:func:`to_slots` as numpy fancy indexing (the reference its compiled pass is tested against)."""
    L, h, w = valid.shape
    out = np.zeros_like(values)
    occ = np.zeros((L, h, w), bool)
    k, y, x = np.nonzero(valid)
    s = slot_of[k, y, x]
    out[s, y, x] = values[k, y, x]
    occ[s, y, x] = True
    return out, occ


# ------------------------------------------------------------------------------------------ layout

@dataclass
class TileLayout:
    """Where every (slot, block) lives in the texture (Algorithm 4.1)."""

    width: int
    height: int                 # layer size
    tile: int
    full_layers: int
    order: str                  # "block" | "layer"
    block_counts: np.ndarray    # (By, Bx) tiles per block (slots beyond the full layers)
    first_index: np.ndarray     # (By, Bx) block-first: index of the block's first tile
    layer_index: np.ndarray     # (Lt, By, Bx) layer-first: tile index per tiled slot (-1: none)
    tiles: int                  # number of tiles

    @property
    def tiles_in_row(self) -> int:
        return self.width // self.tile

    @property
    def tile_rows(self) -> int:
        return -(-self.tiles // self.tiles_in_row)

    @property
    def texture_height(self) -> int:
        return self.full_layers * self.height + self.tile_rows * self.tile


def make_layout(block_counts: np.ndarray, width: int, height: int, tile: int, full_layers: int,
                order: str) -> TileLayout:
    """Tile indices from block counts by prefix sums, block-first or layer-first, blocks row-major (§4.1.3)."""
    if order not in ORDERS:
        raise ValueError(f"unknown packing order '{order}' (choose from {', '.join(ORDERS)})")
    counts = np.asarray(block_counts, np.int64)
    flat = counts.ravel()
    first = (np.cumsum(flat) - flat).reshape(counts.shape)
    lt = int(flat.max()) if flat.size else 0
    layer_index = np.full((lt,) + counts.shape, -1, np.int64)
    offset = 0
    for j in range(lt):
        has = counts > j
        n = int(has.sum())
        idx = np.full(counts.shape, -1, np.int64)
        idx[has] = offset + np.arange(n)   # row-major rank among the blocks that have tile j
        layer_index[j] = idx
        offset += n
    return TileLayout(width, height, tile, full_layers, order, counts, first, layer_index, int(flat.sum()))


def slot_texel(layout: TileLayout, x: np.ndarray, y: np.ndarray, slot: np.ndarray):
    """Algorithm 4.1: texture coordinates (tx, ty) of layer pixel (x, y) in ``slot``, and whether that slot is
    stored at all (full layers always; tiled slots only below the block's count)."""
    x, y, slot = (np.asarray(a, np.int64) for a in (x, y, slot))
    t = layout.tile
    full = slot < layout.full_layers
    bx, by = x // t, y // t
    j = slot - layout.full_layers
    if layout.order == "layer":
        jj = np.clip(j, 0, max(layout.layer_index.shape[0] - 1, 0))
        tile_index = layout.layer_index[jj, by, bx] if layout.layer_index.shape[0] else np.full_like(x, -1)
        stored = full | ((j >= 0) & (j < layout.block_counts[by, bx]) & (tile_index >= 0))
    else:
        tile_index = layout.first_index[by, bx] + j
        stored = full | ((j >= 0) & (j < layout.block_counts[by, bx]))
    tx_tile = (tile_index % layout.tiles_in_row) * t + x % t
    ty_tile = layout.full_layers * layout.height + (tile_index // layout.tiles_in_row) * t + y % t
    tx = np.where(full, x, tx_tile)
    ty = np.where(full, slot * layout.height + y, ty_tile)
    return np.where(stored, tx, 0), np.where(stored, ty, 0), stored


def pack(slot_colour: np.ndarray, slot_occupied: np.ndarray, layout: TileLayout):
    """Packed texture (Fig. 4.7) and its ternary pixel mask (§4.5.2): 1 = a fragment, 0 = an empty slot before
    the pixel's last fragment, ANY = after it, or texels no slot maps to. One compiled pass: the full layers row by
    row, then each stored tile copied to its :func:`slot_texel` address, looked up once per tile (the bits of
    :func:`pack_reference`)."""
    L, h, w = slot_occupied.shape
    tex = np.zeros((layout.texture_height, w, 3), np.uint8)
    mask = np.full((layout.texture_height, w), ANY, np.int8)
    bad = _passes()["_pack_pass"](np.ascontiguousarray(slot_colour, np.uint8),
                                  np.ascontiguousarray(slot_occupied, np.bool_), _address(layout), np.int8(ANY), tex,
                                  mask)
    if bad >= 0:
        raise ValueError(f"slot {bad} holds fragments in blocks whose count excludes it")
    return tex, mask


def fetch(layout: TileLayout, texture: np.ndarray, x: np.ndarray, y: np.ndarray, slot: np.ndarray,
          want: np.ndarray, dest: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Algorithm 4.1's lookup in one compiled pass: for every i with ``want[i]``, the texel of layer pixel
    (``x[i]``, ``y[i]``) in ``slot[i]`` copied to row ``dest[i]`` of ``out`` (N, 3) where that slot is stored.
    Returns whether it was (False where not wanted): :func:`slot_texel` for each pixel."""
    stored = np.zeros(len(x), np.bool_)
    _passes()["_fetch_pass"](np.asarray(x, np.int64), np.asarray(y, np.int64), np.asarray(slot, np.int64),
                             np.asarray(want, np.bool_), _address(layout), texture, np.asarray(dest, np.int64), out,
                             stored)
    return stored


def _address(layout: TileLayout) -> tuple:
    """The layout as the compiled passes take it (:func:`_texel`)."""
    layer_index = np.ascontiguousarray(layout.layer_index, np.int64)
    if layer_index.shape[0] == 0:  # no tiled slot: one row of "none" keeps the passes' arguments typed alike
        layer_index = np.full((1,) + tuple(layout.block_counts.shape), -1, np.int64)
    return (int(layout.tile), int(layout.full_layers), int(layout.height), layout.order == "layer", layer_index,
            np.ascontiguousarray(layout.first_index, np.int64), np.ascontiguousarray(layout.block_counts, np.int64),
            int(layout.tiles_in_row))


def _texel(x, y, s, address):
    """:func:`slot_texel` for one pixel and slot: (tx, ty, stored), (0, 0, False) where the slot is not stored."""
    t, full_layers, height = address[0], address[1], address[2]
    if s < full_layers:
        return x, s * height + y, True
    tx0, ty0, stored = _tile_of(s - full_layers, y // t, x // t, address)
    if not stored:
        return 0, 0, False
    return tx0 + x % t, ty0 + y % t, True


def _tile_of(j, by, bx, address):
    """Slot ``j`` beyond the full layers of block (by, bx): (texel column, texel row of the tile's corner, stored),
    (0, 0, False) where the block's count excludes it. The tile passes look it up once per tile."""
    t, full_layers, height, layer_first, layer_index, first_index, block_counts, tiles_in_row = address
    if layer_first:
        tile_index = layer_index[min(j, layer_index.shape[0] - 1), by, bx]
        stored = j < block_counts[by, bx] and tile_index >= 0
    else:
        tile_index = first_index[by, bx] + j
        stored = j < block_counts[by, bx]
    if not stored:
        return 0, 0, False
    return (tile_index % tiles_in_row) * t, full_layers * height + (tile_index // tiles_in_row) * t, True


def _pack_pass(colour, occupied, address, any_value, tex, mask):
    """The full layers row by row, then every stored tile as a block copy (its address looked up once); returns the
    lowest slot that holds a fragment in a block whose count excludes it (-1: none)."""
    t, full_layers, height = address[0], address[1], address[2]
    L, h, w = occupied.shape
    last = np.full((h, w), -1, np.int64)
    for s in range(L):
        for y in range(h):
            for x in range(w):
                if occupied[s, y, x]:
                    last[y, x] = s
    for s in range(min(full_layers, L)):
        for y in range(h):
            for x in range(w):
                for c in range(3):
                    tex[s * height + y, x, c] = colour[s, y, x, c]
                mask[s * height + y, x] = 1 if occupied[s, y, x] else (0 if s < last[y, x] else any_value)
    bad = -1
    for s in range(full_layers, L):
        for by in range(h // t):
            for bx in range(w // t):
                tx0, ty0, stored = _tile_of(s - full_layers, by, bx, address)
                for dy in range(t):
                    y = by * t + dy
                    for dx in range(t):
                        x = bx * t + dx
                        if not stored:
                            if occupied[s, y, x] and bad < 0:
                                bad = s
                            continue
                        for c in range(3):
                            tex[ty0 + dy, tx0 + dx, c] = colour[s, y, x, c]
                        mask[ty0 + dy, tx0 + dx] = 1 if occupied[s, y, x] else (0 if s < last[y, x] else any_value)
    return bad


def _fetch_pass(x, y, slot, want, address, texture, dest, out, stored):
    for i in range(len(x)):
        if not want[i]:
            continue
        tx, ty, ok = _texel(x[i], y[i], slot[i], address)
        stored[i] = ok
        if ok:
            for c in range(3):
                out[dest[i], c] = texture[ty, tx, c]


def pack_reference(slot_colour: np.ndarray, slot_occupied: np.ndarray, layout: TileLayout):
    """:func:`pack` as numpy gathers per slot over :func:`slot_texel` (the reference its compiled pass is tested
    against)."""
    L, h, w = slot_occupied.shape
    tex = np.zeros((layout.texture_height, w, 3), np.uint8)
    mask = np.full((layout.texture_height, w), ANY, np.int8)
    last = np.where(slot_occupied, np.arange(L)[:, None, None], -1).max(axis=0)
    yy, xx = np.mgrid[0:h, 0:w]
    for s in range(L):
        tx, ty, stored = slot_texel(layout, xx, yy, np.full_like(xx, s))
        occ = slot_occupied[s]
        if (occ & ~stored).any():
            raise ValueError(f"slot {s} holds fragments in blocks whose count excludes it")
        sel = stored
        tex[ty[sel], tx[sel]] = slot_colour[s][sel]
        m = np.where(occ, 1, np.where(s < last, 0, ANY)).astype(np.int8)
        mask[ty[sel], tx[sel]] = m[sel]
    return tex, mask


def unpack(tex: np.ndarray, mask: np.ndarray, layout: TileLayout, layers: int):
    """Slot arrays back from a packed texture: (colour (L, H, W, 3), mask (L, H, W) as stored, stored (L, H, W)).
    One compiled pass, tile by tile (each tile's address looked up once), with the results of
    :func:`unpack_reference`."""
    h, w = layout.height, layout.width
    colour = np.zeros((layers, h, w, 3), np.uint8)
    m = np.zeros((layers, h, w), np.uint8)
    stored = np.zeros((layers, h, w), bool)
    _passes()["_unpack_pass"](np.ascontiguousarray(tex, np.uint8), np.ascontiguousarray(mask), _address(layout),
                              colour, m, stored)
    return colour, m, stored


def _unpack_pass(tex, mask, address, colour, m, stored):
    t, full_layers, height = address[0], address[1], address[2]
    L, h, w = stored.shape
    for s in range(min(full_layers, L)):
        for y in range(h):
            for x in range(w):
                stored[s, y, x] = True
                for c in range(3):
                    colour[s, y, x, c] = tex[s * height + y, x, c]
                m[s, y, x] = mask[s * height + y, x]
    for s in range(full_layers, L):
        for by in range(h // t):
            for bx in range(w // t):
                tx0, ty0, ok = _tile_of(s - full_layers, by, bx, address)
                if not ok:
                    continue
                for dy in range(t):
                    for dx in range(t):
                        y, x = by * t + dy, bx * t + dx
                        stored[s, y, x] = True
                        for c in range(3):
                            colour[s, y, x, c] = tex[ty0 + dy, tx0 + dx, c]
                        m[s, y, x] = mask[ty0 + dy, tx0 + dx]


def unpack_reference(tex: np.ndarray, mask: np.ndarray, layout: TileLayout, layers: int):
    """:func:`unpack` as numpy gathers per slot over :func:`slot_texel` (the reference its compiled pass is tested
    against)."""
    h, w = layout.height, layout.width
    yy, xx = np.mgrid[0:h, 0:w]
    colour = np.zeros((layers, h, w, 3), np.uint8)
    m = np.zeros((layers, h, w), np.uint8)
    stored = np.zeros((layers, h, w), bool)
    for s in range(layers):
        tx, ty, st = slot_texel(layout, xx, yy, np.full_like(xx, s))
        colour[s] = np.where(st[..., None], tex[ty, tx], 0)
        m[s] = np.where(st, mask[ty, tx], 0)
        stored[s] = st
    return colour, m, stored


def relocate_back(slot_colour: np.ndarray, slot_mask: np.ndarray, counts: np.ndarray):
    """Client side of §4.1.4: the k-th set slot of a pixel holds its k-th fragment; ``counts`` (H, W) = fragments
    per pixel from the client's own depth peeling. Returns (layer colour (L, H, W, 3), layer valid (L, H, W)).
    One compiled pass over the pixels, with the results of :func:`relocate_back_reference`."""
    out = np.zeros_like(slot_colour)
    valid = np.zeros(slot_mask.shape, bool)
    _passes()["_relocate_back_pass"](np.ascontiguousarray(slot_colour), np.ascontiguousarray(slot_mask),
                                     np.ascontiguousarray(counts, np.int64), out, valid)
    return out, valid


def _relocate_back_pass(slot_colour, slot_mask, counts, out, valid):
    L, h, w = slot_mask.shape
    for y in range(h):
        for x in range(w):
            rank = np.int64(-1)  # the reference's cumulative sum of the mask values, minus one
            for s in range(L):
                rank += np.int64(slot_mask[s, y, x])
                if slot_mask[s, y, x] > 0 and rank < counts[y, x]:
                    if rank >= L:  # mask values above 1 ranked past the last layer (the reference's IndexError)
                        raise IndexError("a slot's mask ranks its fragment past the last layer")
                    for c in range(out.shape[3]):
                        out[rank, y, x, c] = slot_colour[s, y, x, c]
                    valid[rank, y, x] = True


def relocate_back_reference(slot_colour: np.ndarray, slot_mask: np.ndarray, counts: np.ndarray):
    """:func:`relocate_back` as numpy expressions per slot (the reference its compiled pass is tested against)."""
    L, h, w = slot_mask.shape
    rank = np.cumsum(slot_mask.astype(np.int64), axis=0) - 1
    out = np.zeros_like(slot_colour)
    valid = np.zeros((L, h, w), bool)
    for s in range(L):
        sel = (slot_mask[s] > 0) & (rank[s] < counts)
        k = rank[s][sel]
        ys, xs = np.nonzero(sel)
        out[k, ys, xs] = slot_colour[s][ys, xs]
        valid[k, ys, xs] = True
    return out, valid


# ------------------------------------------------------------------------------------------ the server's stage

def pack_stage(depth: np.ndarray, valid: np.ndarray, colour: np.ndarray, tile: int, full_layers: int, order: str,
               relocation: bool = True, fill: bool = True, device=None):
    """The server's ``pack`` stage on peeled layers (``depth``, ``valid`` (L, H, W); ``colour`` (L, H, W, 3) uint8):
    relocation (Algorithm 2) or identity slots, block counts beyond the ``full_layers``, the layout, the packed
    texture and mask (Fig. 4.7, §4.5.2), colour filling (§4.1.5). On a Dr.Jit ``device`` (a Mitsuba tracer's) the
    same results from its kernels (:func:`methods.layered_pvs.device.pack_layers`); else these compiled passes.
    Returns (texture (rows, W, 3) uint8, mask (rows, W) int8, block counts (By, Bx), layout, fragments
    relocated)."""
    if device is not None:
        from methods.layered_pvs import device as kernels

        return kernels.pack_layers(device, depth, valid, colour, tile, full_layers, order, relocation, fill)
    slot_of = relocate(depth, valid, tile) if relocation else identity_slots(valid)
    relocated = int((slot_of[valid] != np.nonzero(valid)[0]).sum())
    slot_colour, occupied = to_slots(colour, valid, slot_of)
    counts = np.maximum(block_layer_counts(occupied, tile) - full_layers, 0)
    layout = make_layout(counts, valid.shape[2], valid.shape[1], tile, full_layers, order)
    tex, mask = pack(slot_colour, occupied, layout)
    if fill:
        tex = colour_fill(tex, mask == 1, tile)
    return tex, mask, counts, layout, relocated


# ------------------------------------------------------------------------------------------ colour filling

def colour_fill(tex: np.ndarray, filled: np.ndarray, tile: int, max_rounds: int | None = None) -> np.ndarray:
    """§4.1.5: inside every tile, empty texels take the average colour of their non-empty 4-neighbours, round after
    round, until no empty texel is left (a tile with no fragment stays as it is). One compiled pass, tile by tile
    (a tile's rounds depend on that tile only), with the float32 sums of :func:`colour_fill_reference`."""
    out = np.array(tex, np.float32, order="C")  # copies: the pass fills in place
    have = np.array(filled, np.bool_)
    _passes()["_fill_pass"](out, have, int(tile), int(max_rounds or 2 * tile))
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _fill_pass(out, have, tile, rounds):
    h, w = have.shape
    new = np.zeros((tile, tile), np.bool_)
    avg = np.zeros((tile, tile, 3), np.float32)
    zero = np.float32(0.0)
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            for _ in range(rounds):
                # Every empty texel from the state at the start of the round, then all of them written.
                grew = False
                for y in range(y0, y1):
                    for x in range(x0, x1):
                        new[y - y0, x - x0] = False
                        if have[y, x]:
                            continue
                        s0, s1, s2, n = zero, zero, zero, zero
                        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):  # up, down, left, right
                            yy, xx = y + dy, x + dx
                            if yy < y0 or yy >= y1 or xx < x0 or xx >= x1 or not have[yy, xx]:
                                continue
                            s0 += out[yy, xx, 0]
                            s1 += out[yy, xx, 1]
                            s2 += out[yy, xx, 2]
                            n += np.float32(1.0)
                        if n > 0:
                            new[y - y0, x - x0] = True
                            avg[y - y0, x - x0, 0] = s0 / n
                            avg[y - y0, x - x0, 1] = s1 / n
                            avg[y - y0, x - x0, 2] = s2 / n
                            grew = True
                if not grew:
                    break
                for y in range(y0, y1):
                    for x in range(x0, x1):
                        if new[y - y0, x - x0]:
                            have[y, x] = True
                            for c in range(3):
                                out[y, x, c] = avg[y - y0, x - x0, c]


def colour_fill_reference(tex: np.ndarray, filled: np.ndarray, tile: int, max_rounds: int | None = None) -> np.ndarray:
    """:func:`colour_fill` as whole-texture numpy rounds (the reference its compiled pass is tested against)."""
    out = tex.astype(np.float32)
    have = np.asarray(filled, bool).copy()
    rounds = max_rounds or 2 * tile
    for _ in range(rounds):
        if have.all():
            break
        cols = _neighbour_views(np.moveaxis(out, -1, 0), tile, 0.0)
        hv = _neighbour_views(have.astype(np.float32), tile, 0.0)
        n = sum(hv)
        s = sum(c * m[None] for c, m in zip(cols, hv))
        new = ~have & (n > 0)
        if not new.any():
            break
        avg = np.moveaxis(s / np.maximum(n, 1)[None], 0, -1)
        out[new] = avg[new]
        have |= new
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
