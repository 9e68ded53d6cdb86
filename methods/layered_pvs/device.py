"""The layered SVGF (seed 002 §4.4.1) and the server's pack stage (§4.1.3-§4.1.5) as Dr.Jit kernels on the run's
Mitsuba variant: one code path, vectorised and multi-threaded on ``llvm_ad_rgb`` and on the GPU on ``cuda_ad_rgb``
(the core's device kernels, suite.core.device).

:func:`svgf_passes` is :func:`methods.layered_pvs.server._svgf_passes` (the numba kernel Embree runs): the same
grids in the kernel's (H, W, L[, 3]) layout, one lane per (pixel, layer) slot, the numba kernel's operations in its
order, in float32 (the numba kernel's are float64): colour, variance, normals, depth, and positions relative to a
point of the view, so that the plane distances keep float32 precision wherever the scene lies. The stage rounds its
result to float32 anyway; the two agree to float32 rounding (relative 1e-5 at most on a 480x270, 4-layer update of
``living_room``; tests/methods/layered_pvs/test_device.py compares them, a scene 1e4 away from the origin
included), and float32 halves the bytes each tap gathers and doubles the lanes of every vector operation on
``llvm_ad_rgb`` (367 -> 224 ms for the five passes of that update, 2 cores, interleaved). The grids go up once per
update and the filtered illumination comes back once (counted copies); between the passes everything stays on the
device, and every pass is the same compiled kernel (its step is read from memory).

:func:`pack_layers` is :func:`methods.layered_pvs.packing.pack_stage`'s host passes (relocation, packing, colour
filling) with their results bit for bit (below, "packing").
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from functools import partial
from types import SimpleNamespace

import numpy as np

from suite.core.device import rng as device_rng
from suite.core.device.context import packet_rows, read_rows
from suite.core.rng import dim_hashes, pcg_np
from suite.core.trace.alpha import MAX_ALPHA_LAYERS

UNROLL_LIGHTS = 16   # at most this many lights: DeviceLights.unrolled
B3 = (1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16)    # the 5x5 B3-spline kernel of the numba pass


SVGF_ROW = 4  # float32 values per slot in the SVGF pass's tables (a power of two: one packet gather)


def _svgf_pass(dev, shape, frags, cv, pv, nr, dep, step: int, pix_angle: float, shift_scale: float,
               sigma_l: float, sigma_n: float):
    """One à-trous pass with tap spacing ``step``: the grids are flat (H, W, L) tables of rows of four float32
    (``cv``: colour and variance; ``pv``: position relative to a point of the view (:func:`_relative`) and, where
    the slot holds a fragment, the number of fragments at its pixel (0 elsewhere); ``nr``: normal and 0), one packet
    gather per slot read; the lanes the slots that hold a fragment (``frags``, their flat indices, ascending);
    returns the new ``cv`` table (0 in empty slots, as the numba pass leaves them). The numba pass's operations in
    its order, in float32 (module docstring)."""
    dr, F, I32, U = dev.dr, dev.Float, dev.Int32, dev.UInt32
    H, W, L = shape
    X = dev.m.ArrayXf
    size = dr.width(frags)

    def row(table, index, active=True):
        return read_rows(dev, table, index, SVGF_ROW, active)

    pix = frags // L
    y, x = I32(pix // W), I32(pix % W)
    step_i = dev.opaque(I32, int(step))
    step_f = dev.opaque(F, float(step))
    int_n = int(sigma_n) if sigma_n == math.floor(sigma_n) and 0 < sigma_n <= 1024 else 0
    r = row(pv, frags)
    p = dev.Vector3f(r[0], r[1], r[2])
    r = row(nr, frags)
    n = dev.Vector3f(r[0], r[1], r[2])
    r = row(cv, frags)
    c, v = dev.Vector3f(r[0], r[1], r[2]), r[3]
    lc = (0.2126 * c.x + 0.7152 * c.y) + 0.0722 * c.z
    sd = dr.sqrt(dr.maximum(v, 0.0))
    foot = dr.gather(F, dep, frags) * dev.opaque(F, float(pix_angle))
    shift_scale = dev.opaque(F, float(shift_scale))
    sigma_l = dev.opaque(F, float(sigma_l))

    def b3(k):  # B3[k + 2] for an offset k in -2..2 (the table's values, selected)
        a = dr.abs(k)
        return dr.select(a == 0, B3[2], dr.select(a == 1, B3[1], B3[0]))

    # The 25 taps as a symbolic loop (one small kernel; written out, LLVM took seconds to compile each pass shape).
    def body(t, wsum, vsum, acc):
        ty, tx = I32(t // 5) - 2, I32(t % 5) - 2
        yy, xx = y + ty * step_i, x + tx * step_i
        inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
        base = U(dr.select(inside, yy * W + xx, 0)) * L
        radius = dr.sqrt(F(tx * tx + ty * ty))            # math.sqrt of the same whole number, rounded to float32
        shift = shift_scale * foot * radius * step_f
        # §4.4.1: of the fragments at the tap, the one closest to the centre fragment's shifted plane; the search
        # stops at the tap's first empty layer (the gather's mask carries it on). The first layer is read before the
        # loop, and its row's fragment count bounds the loop: a tap with one fragment (most of them) enters no loop
        # iteration, where the loop would read the empty second layer to find its end (the same fragments visited).
        def consider(m, q, alive, best, best_d, best_pd):
            alive = alive & (q[3] != 0.0)
            pd = (n.x * (q[0] - p.x) + n.y * (q[1] - p.y)) + n.z * (q[2] - p.z)
            dd = dr.abs(pd - shift)
            better = alive & (dd < best_d)
            return alive, dr.select(better, m, best), dr.select(better, dd, best_d), dr.select(better, pd, best_pd)

        def search(m, alive, best, best_d, best_pd):
            return (m + 1, *consider(m, row(pv, base + U(m), alive), alive, best, best_d, best_pd))

        q0 = row(pv, base, inside)
        count = I32(dr.select(inside, q0[3], 0.0))
        first = consider(dr.zeros(I32, size), q0, inside, dr.full(I32, -1, size), dr.full(F, 3.0e38, size),
                         dr.zeros(F, size))
        _, _, best, best_d, best_pd = dr.while_loop((dr.full(I32, 1, size), *first),
                                                    lambda m, alive, *_: alive & (m < count), search)
        found = best >= 0
        j = base + U(dr.maximum(best, 0))
        rb = row(cv, j, found)
        cb, vb = dev.Vector3f(rb[0], rb[1], rb[2]), rb[3]
        rn = row(nr, j, found)
        nb = dev.Vector3f(rn[0], rn[1], rn[2])
        ln = (0.2126 * cb.x + 0.7152 * cb.y) + 0.0722 * cb.z
        ndot = (n.x * nb.x + n.y * nb.y) + n.z * nb.z
        ok = found & (ndot > 0.0)
        if int_n > 0:
            wn, b, e = None, ndot, int_n
            while e:
                if e & 1:
                    wn = b if wn is None else wn * b
                b = b * b
                e >>= 1
        else:
            wn = dr.power(dr.select(ok, ndot, 1.0), float(sigma_n))
        wn = dr.select(ndot == 1.0, 1.0, wn)
        dist_px = radius * step_f
        wzl = dr.exp(-(dr.abs(best_pd) / (foot * (dist_px + 1.0) + 1e-12)
                       + dr.abs(lc - ln) / (sigma_l * sd + 1e-10)))
        wgt = F(b3(ty)) * F(b3(tx)) * wn * wzl
        wsum = dr.select(ok, wsum + wgt, wsum)
        vsum = dr.select(ok, vsum + wgt * wgt * vb, vsum)
        acc = dr.select(ok, dev.Vector3f(acc.x + wgt * cb.x, acc.y + wgt * cb.y, acc.z + wgt * cb.z), acc)
        return t + 1, wsum, vsum, acc

    _, wsum, vsum, acc = dr.while_loop((dr.zeros(U, size), dr.zeros(F, size), dr.zeros(F, size),
                                        dr.zeros(dev.Vector3f, size)), lambda t, *_: t < 25, body)
    kept = wsum > 1e-30  # the centre tap alone weighs 9/64: a threshold for empty sums only
    out = dr.zeros(F, H * W * L * SVGF_ROW)
    new_c = dr.select(kept, acc / wsum, c)
    new_v = dr.select(kept, vsum / (wsum * wsum), v)
    dr.scatter(out, X(new_c.x, new_c.y, new_c.z, new_v), frags)
    dr.eval(out)
    return out


def _colour(dev, cv, index):
    """The (N, 3) colour of the ``cv`` table's rows ``index`` (UInt32), copied to the host (colour only, float32
    values as float64)."""
    rows = read_rows(dev, cv, index, SVGF_ROW)
    return dev.to_host(dev.Vector3f(rows[0], rows[1], rows[2]), np.float32).astype(np.float64)


def _relative(positions: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Float64 positions minus the centre of the valid ones' bounds: the pass uses only differences of positions
    (the distance of a tap's fragment to the centre fragment's plane), and relative to a point of the view they keep
    float32 precision however far from the world origin the scene lies."""
    if not valid.any():
        return positions
    pts = positions[valid]
    return positions - 0.5 * (pts.min(axis=0) + pts.max(axis=0))


SVGF_PARAMS = (1.0, 4.0, 128.0)  # shift_scale, sigma_l, sigma_n: server._svgf_passes' defaults


def svgf_passes(dev, col, var, pos, nrm, val, dep, pix_angle: float, iterations: int,
                shift_scale: float = SVGF_PARAMS[0], sigma_l: float = SVGF_PARAMS[1],
                sigma_n: float = SVGF_PARAMS[2]) -> np.ndarray:
    """:func:`methods.layered_pvs.server._svgf_passes` on ``dev``: (H, W, L[, 3]) float64 grids (bool ``val``) in,
    the filtered (H, W, L, 3) float64 illumination out."""
    shape = tuple(np.shape(val))
    flat3 = lambda a: np.ascontiguousarray(a, np.float64).reshape(-1, 3)  # noqa: E731
    valid = np.asarray(val, bool).reshape(-1)
    c, p, n = flat3(col), _relative(flat3(pos), valid), flat3(nrm)
    up = lambda columns: dev.to_device(packet_rows(columns, np.float32, SVGF_ROW), dev.Float)  # noqa: E731
    cv = up([c, np.asarray(var, np.float64).reshape(-1)])
    per_pixel = valid.reshape(-1, shape[-1])
    pv = up([p, np.where(valid, np.repeat(per_pixel.sum(axis=1), shape[-1]), 0)])  # fragments at the slot's pixel
    nr = up([n])
    d = dev.to_device(np.ascontiguousarray(dep, np.float32).reshape(-1), dev.Float)
    frags = dev.dr.compress(dev.to_device(valid, dev.Bool))  # the lanes: the slots that hold a fragment
    for it in range(int(iterations)):
        cv = _svgf_pass(dev, shape, frags, cv, pv, nr, d, 1 << it, pix_angle, shift_scale, sigma_l, sigma_n)
    return _colour(dev, cv, dev.arange(len(valid))).reshape(shape + (3,))


def denoise(dev, layers, frag, illum, var, pix_angle: float, iterations: int) -> np.ndarray:
    """``server.denoise_fragments`` from fragments ``dev`` made (:func:`twins`): the SVGF's tables are built
    there from the fragments' positions and normals in place, their illumination and sample variance (uploaded, N
    values each) and depths, the spatial variance (``server.spatial_variance``: 3x3 luminance moments within the
    fragment's layer, in the numpy sums' order) included, instead of host grids of every slot going up. Returns the
    filtered (N, 3) illumination in fragment order, the values of the host grids' path to float32 rounding."""
    dr, F64, U, I32 = dev.dr, dev.Float64, dev.UInt32, dev.Int32
    X = dev.m.ArrayXf
    L, H, W = layers.prim.shape
    k, y, x = (np.asarray(a, np.int64) for a in frag.index)
    n = len(k)
    size = L * H * W
    made = twins(frag, dev)
    # the passes are float32: the light, variance and depth go up as float32 (the spatial variance's sums in float64)
    c = dev.Vector3d(dev.to_device(np.asarray(illum, np.float32), dev.Vector3f))
    sv_ = dev.to_device(np.asarray(var, np.float32), dev.Float)
    t = dev.to_device(np.asarray(layers.t)[k, y, x].astype(np.float32), dev.Float)
    kk, yy, xx = (dev.to_device(a.astype(np.int32), I32) for a in (k, y, x))
    L_, H_, W_ = (dev.opaque(I32, v) for v in (L, H, W))
    slot_layer = U((kk * H_ + yy) * W_ + xx)   # (L, H, W): the spatial variance's grids
    slot_pixel = U((yy * W_ + xx) * L_ + kk)   # (H, W, L): the SVGF's tables
    lum = (c.x * 0.2126 + c.y * 0.7152) + c.z * 0.0722
    grids = [dr.zeros(F64, size) for _ in range(3)]  # lum, lum^2, occupancy (0 where no fragment)
    for g, value in zip(grids, (lum, lum * lum, dr.full(F64, 1.0, n))):
        dr.scatter(g, value, slot_layer)
    dr.eval(*grids)
    s = [dr.zeros(F64, n) for _ in range(3)]
    for dy in (-1, 0, 1):  # the 3x3 sums in the order of server.spatial_variance's (dy, dx) loop
        for dx in (-1, 0, 1):
            ny, nx = yy + dy, xx + dx
            inside = (ny >= 0) & (ny < H_) & (nx >= 0) & (nx < W_)
            j = U((kk * H_ + ny) * W_ + nx)
            s = [acc + dr.gather(F64, g, j, inside) for acc, g in zip(s, grids)]
    cnt = dr.maximum(s[2], 1.0)
    mean = s[0] / cnt
    spatial = dr.maximum(s[1] / cnt - mean * mean, 0.0)
    var_g = dr.maximum(spatial, F64(sv_))
    F = dev.Float
    cv, pv, nr = (dr.zeros(F, size * SVGF_ROW) for _ in range(3))
    pos, nrm = made.position, made.normal
    # positions relative to one fragment's (_relative: float32 differences keep their precision far from the origin)
    ref = dr.gather(dev.Point3d, pos, dr.zeros(U, 1))
    zero = dr.zeros(F, n)
    dr.scatter(cv, X(F(c.x), F(c.y), F(c.z), F(var_g)), slot_pixel)
    # the fragments at each pixel (sums of ones: exact in any order)
    pixel = U(yy * W_ + xx)
    at_pixel = dr.zeros(F, H * W)
    dr.scatter_add(at_pixel, dr.full(F, 1.0, n), pixel)
    dr.eval(at_pixel)
    dr.scatter(pv, X(F(pos.x - ref.x), F(pos.y - ref.y), F(pos.z - ref.z), dr.gather(F, at_pixel, pixel)), slot_pixel)
    dr.scatter(nr, X(F(nrm.x), F(nrm.y), F(nrm.z), zero), slot_pixel)
    d = dr.zeros(F, size)
    dr.scatter(d, F(t), slot_pixel)
    dr.eval(cv, pv, nr, d)
    frags = dr.compress(dr.gather(F, pv, dev.arange(size) * SVGF_ROW + 3) != 0.0)  # the slots with a fragment
    for it in range(int(iterations)):
        cv = _svgf_pass(dev, (H, W, L), frags, cv, pv, nr, d, 1 << it, pix_angle, *SVGF_PARAMS)
    return _colour(dev, cv, slot_pixel)


# ------------------------------------------------------------------------------------------ packing (§4.1.3-§4.1.5)
#
# The pack stage on the device: fragment relocation (Algorithm 2), block counts, the packed texture and its ternary
# mask (Fig. 4.7, §4.5.2) and colour filling (§4.1.5), with the results of methods/layered_pvs/packing.py's compiled
# passes (bit for bit: integer work, float64 depth means and float32 colour sums in the same order). Relocation and
# colour filling go round after round inside a block (a tile), each round reading the state at its start, as one
# CUDA block does in the thesis; here a lane takes a whole block (a tile): the block's slots are copied into the
# lane's local memory (``dr.alloc_local``), its rounds run as symbolic loops over its pixels in the numba passes'
# order, and the result is written back: one kernel for every block.


def _uint8(dev):
    """The variant's UInt8 type (the Mitsuba variant module has none)."""
    import importlib

    return importlib.import_module(dev.Float.__module__).UInt8


def _block_layer_counts(dev, slot_frag, shape, tile: int):
    """:func:`methods.layered_pvs.packing.block_layer_counts` of the occupied slots of ``slot_frag`` (flat (L, H, W)
    Int32, -1 where empty): per block (row-major), 1 + the highest slot any of its pixels uses. Lanes go block after
    block, each block's pixels row-major, so one block reduction gives the blocks' maxima."""
    dr, I32, U = dev.dr, dev.Int32, dev.UInt32
    L, H, W = shape
    hw, t2, bx_count = H * W, tile * tile, W // tile
    blk = dr.repeat(dr.arange(U, (H // tile) * bx_count), t2)
    local = dr.tile(dr.arange(U, t2), (H // tile) * bx_count)
    pix = U((I32(blk // bx_count) * tile + I32(local // tile)) * W + I32(blk % bx_count) * tile + I32(local % tile))
    used = dr.zeros(I32, dr.width(pix))
    for s in range(L):
        used = dr.select(dr.gather(I32, slot_frag, pix + s * hw) >= 0, s + 1, used)
    return dr.block_reduce(dr.ReduceOp.Max, used, t2)


_NEIGHBOURS = ((-1, 0), (1, 0), (0, -1), (0, 1))  # up, down, left, right: the numba passes' order


def _neighbour(dev, i, tile: int, dy: int, dx: int):
    """(inside the block, local index) of the neighbour (dy, dx) of the block's pixel ``i`` (its own index where
    outside)."""
    dr, I32, U = dev.dr, dev.Int32, dev.UInt32
    ly, lx = I32(i // tile) + dy, I32(i % tile) + dx
    inside = (ly >= 0) & (ly < tile) & (lx >= 0) & (lx < tile)
    return inside, dr.select(inside, U(ly * tile + lx), i)


def _block_loop(dev, n: int, count: int, body, *state):
    """``for i in range(count): state = body(i, *state)`` as a symbolic loop over ``n`` lanes."""
    dr, U = dev.dr, dev.UInt32
    out = dr.while_loop((dr.zeros(U, n),) + tuple(state), lambda i, *_: i < count,
                        lambda i, *st: (i + 1,) + tuple(body(i, *st)))
    return out[1:]


def relocate_slots(dev, slot_frag, slot_depth, shape, tile: int, max_rounds: int = 64):
    """:func:`methods.layered_pvs.packing.relocate`'s pass (Algorithm 2) on the device, a lane per block that has
    two layers or more. ``slot_frag`` (Int32: the fragment index a slot holds, -1 for none) and ``slot_depth``
    (Float64, inf where empty) are flat (L, H, W) arrays; returns ``slot_frag`` relocated."""
    dr, I32, U, F64 = dev.dr, dev.Int32, dev.UInt32, dev.Float64
    L, H, W = shape
    hw, t2 = H * W, tile * tile
    bx_count = W // tile
    n_block = _block_layer_counts(dev, slot_frag, shape, tile)
    work = dr.compress(n_block >= 2)
    n = dr.width(work)
    if n == 0:
        return slot_frag
    nb = dr.gather(I32, n_block, work)
    corner = U(work // bx_count) * (tile * W) + U(work % bx_count) * tile   # the block's first pixel

    def address(j):  # slot array index of the block's local slot j = s * t2 + i
        i = j % t2
        return (j // t2) * hw + corner + (i // tile) * W + i % tile

    frag, dep = dr.alloc_local(I32, L * t2), dr.alloc_local(F64, L * t2)
    moved = dr.alloc_local(I32, t2)

    def load(j, frag, dep):
        frag[j] = dr.gather(I32, slot_frag, address(j))
        dep[j] = dr.gather(F64, slot_depth, address(j))
        return frag, dep

    frag, dep = _block_loop(dev, n, L * t2, load, frag, dep)

    def layer(k, frag, dep, moved):
        kk = U(k)

        def decide(i, any_move, frag, dep, moved):
            remaining = dr.zeros(I32, n)
            for s in range(L):
                remaining += I32((frag[s * t2 + i] >= 0) & (s >= k))
            d = dep[kk * t2 + i]
            closer = dr.zeros(dev.Bool, n)
            for dy, dx in _NEIGHBOURS:
                inside, j = _neighbour(dev, i, tile, dy, dx)
                nn, nc = dep[(kk + 1) * t2 + j], dep[kk * t2 + j]
                closer |= inside & dr.isfinite(nn) & (dr.abs(d - nn) < dr.abs(d - nc))
            move = (frag[kk * t2 + i] >= 0) & (remaining < nb - k) & closer
            moved[i] = I32(move)
            return any_move | move, frag, dep, moved

        def shift(i, frag, dep, moved):
            # The fragment goes one slot back with the run behind it, up to the pixel's first gap after k.
            move = moved[i] != 0
            f = [frag[s * t2 + i] for s in range(L)]
            z = [dep[s * t2 + i] for s in range(L)]
            gap = dr.full(I32, L, n)
            for s in range(L - 1, 0, -1):
                gap = dr.select((s > k) & (f[s] < 0), s, gap)
            for s in range(L):
                behind = (s > k) & (s <= gap) if s else dr.zeros(dev.Bool, n)
                nf = dr.select(s == k, -1, dr.select(behind, f[s - 1], f[s])) if s else dr.select(s == k, -1, f[s])
                nz = dr.select(behind, z[s - 1], z[s]) if s else z[s]
                frag[s * t2 + i] = dr.select(move, nf, f[s])
                dep[s * t2 + i] = dr.select(move, nz, z[s])
            return frag, dep, moved

        def mean(i, frag, dep, moved):
            # The emptied slot takes the mean depth of the neighbours' next-slot fragments (after the shifts), else
            # its own next slot's (the fragment that moved).
            total, count = dr.zeros(F64, n), dr.zeros(I32, n)
            for dy, dx in _NEIGHBOURS:
                inside, j = _neighbour(dev, i, tile, dy, dx)
                nn = dep[(kk + 1) * t2 + j]
                ok = inside & dr.isfinite(nn)
                total = dr.select(ok, total + nn, total)
                count += I32(ok)
            own = dep[(kk + 1) * t2 + i]
            dep[kk * t2 + i] = dr.select(moved[i] != 0, dr.select(count > 0, total / F64(count), own),
                                         dep[kk * t2 + i])
            return frag, dep, moved

        def round_(r, go, frag, dep, moved):
            any_move, frag, dep, moved = _block_loop(dev, n, t2, decide, dr.zeros(dev.Bool, n), frag, dep, moved)
            frag, dep, moved = _block_loop(dev, n, t2, shift, frag, dep, moved)
            frag, dep, moved = _block_loop(dev, n, t2, mean, frag, dep, moved)
            return r + 1, any_move, frag, dep, moved

        _, _, frag, dep, moved = dr.while_loop((dr.zeros(I32, n), dr.full(dev.Bool, True, n), frag, dep, moved),
                                               lambda r, go, *_: go & (r < max_rounds), round_)
        return k + 1, frag, dep, moved

    _, frag, dep, moved = dr.while_loop((dr.zeros(I32, n), frag, dep, moved), lambda k, *_: k < nb - 1,
                                        lambda k, *st: layer(k, *st))

    def store(j, frag):
        dr.scatter(slot_frag, frag[j], address(j))
        return (frag,)

    _block_loop(dev, n, L * t2, store, frag)
    dr.eval(slot_frag)
    return slot_frag


def _texel(dev, x, y, s: int, t):
    """:func:`methods.layered_pvs.packing._texel` for lanes (x, y) and slot ``s``: (tx, ty, stored)."""
    dr, I32, U = dev.dr, dev.Int32, dev.UInt32
    tile, full_layers, height = t["tile"], t["full_layers"], t["height"]
    if s < full_layers:
        return x, y + s * height, dr.full(dev.Bool, True, dr.width(x))
    bi = U((y // tile) * t["bx_count"] + x // tile)
    j = s - full_layers
    count = dr.gather(I32, t["block_counts"], bi)
    if t["layer_first"]:
        index = dr.gather(I32, t["layer_index"], bi + min(j, t["lt"] - 1) * t["blocks"])
        stored = (j < count) & (index >= 0)
    else:
        index = dr.gather(I32, t["first_index"], bi) + j
        stored = j < count
    index = dr.select(stored, index, 0)
    tx = (index % t["tiles_in_row"]) * tile + x % tile
    ty = full_layers * height + (index // t["tiles_in_row"]) * tile + y % tile
    return dr.select(stored, tx, 0), dr.select(stored, ty, 0), stored


def pack_layers(dev, depth: np.ndarray, valid: np.ndarray, colour: np.ndarray, tile: int, full_layers: int,
                order: str, relocation: bool = True, fill: bool = True, max_rounds: int = 64,
                fill_rounds: int | None = None):
    """The server's pack stage (§4.1.3-§4.1.5) on the device: relocation (Algorithm 2, with ``relocation``),
    block counts, layout, packed texture and mask (Fig. 4.7; :func:`.packing.pack`), colour filling (§4.1.5, with
    ``fill``). ``depth`` (L, H, W) float, ``valid`` (L, H, W), ``colour`` (L, H, W, 3) uint8 per layer go up once;
    the block counts come back for the layout (prefix sums on the host, small), its tables go up, and the texture
    and mask come back once. Returns (texture (rows, W, 3) uint8, mask (rows, W) int8, block counts (By, Bx)
    int64, layout, fragments relocated): :mod:`.packing`'s results."""
    from methods.layered_pvs import packing
    from methods.layered_pvs.codecs import ANY

    dr, I32, U, F32, F64 = dev.dr, dev.Int32, dev.UInt32, dev.Float, dev.Float64
    U8 = _uint8(dev)
    L, H, W = np.shape(valid)
    hw = H * W
    by_count, bx_count = H // tile, W // tile
    v = dev.to_device(np.ascontiguousarray(valid, np.bool_).reshape(-1), dev.Bool)
    slot = I32(dr.arange(U, L * hw) // hw)
    slot_frag = dr.select(v, slot, -1)
    if relocation:
        t = dev.to_device(np.ascontiguousarray(depth, np.float32).reshape(-1), F32)
        slot_depth = dr.select(v, F64(t), dr.inf)
        dr.eval(slot_frag, slot_depth)
        slot_frag = relocate_slots(dev, slot_frag, slot_depth, (L, H, W), tile, max_rounds)
    relocated = int(dr.count((slot_frag >= 0) & (slot_frag != slot))[0])
    # Block counts: tiles per block beyond the full layers.
    used = _block_layer_counts(dev, slot_frag, (L, H, W), tile)
    counts = dev.to_host(dr.maximum(used - full_layers, 0), np.int64).reshape(by_count, bx_count)
    layout = packing.make_layout(counts, W, H, tile, full_layers, order)
    address = packing._address(layout)
    up = lambda a: dev.to_device(np.ascontiguousarray(a, np.int32).reshape(-1), I32)  # noqa: E731
    tables = {"tile": tile, "full_layers": full_layers, "height": H, "bx_count": bx_count,
              "blocks": by_count * bx_count, "layer_first": order == "layer", "layer_index": up(address[4]),
              "lt": int(address[4].shape[0]), "first_index": up(address[5]), "block_counts": up(address[6]),
              "tiles_in_row": layout.tiles_in_row}
    rows = layout.texture_height
    if rows == 0:  # no full layer and no tile: nothing to store (no slot is occupied)
        return np.zeros((0, W, 3), np.uint8), np.zeros((0, W), np.int8), counts, layout, relocated
    # The packed texture: every pixel's slots at their texels (Algorithm 4.1), the slot's fragment's colour.
    col = dev.to_device(np.ascontiguousarray(colour, np.uint8).reshape(-1), U8)
    p = dr.arange(U, hw)
    y, x = I32(p // W), I32(p % W)
    frag = [dr.gather(I32, slot_frag, p + s * hw) for s in range(L)]
    last = dr.full(I32, -1, hw)
    for s in range(L):
        last = dr.select(frag[s] >= 0, s, last)
    tex = [dr.zeros(F32, rows * W) for _ in range(3)]
    mask = dr.full(I32, int(ANY), rows * W)
    have_tile = dr.zeros(dev.Bool, (rows // tile) * bx_count)
    bad = []
    for s in range(L):
        tx, ty, stored = _texel(dev, x, y, s, tables)
        occ = frag[s] >= 0
        bad.append(occ & ~stored)
        texel = U(ty * W + tx)
        src = (U(dr.maximum(frag[s], 0)) * hw + p) * 3
        for c in range(3):
            dr.scatter(tex[c], dr.select(occ, F32(dr.gather(U8, col, src + c, occ)), 0.0), texel, stored)
        dr.scatter(mask, dr.select(occ, 1, dr.select(s < last, 0, int(ANY))), texel, stored)
        dr.scatter(have_tile, True, U((ty // tile) * bx_count + tx // tile), stored & occ)
    dr.eval(*tex, mask, have_tile, *bad)
    for s in range(L):
        if dr.any(bad[s])[0]:
            raise ValueError(f"slot {s} holds fragments in blocks whose count excludes it")
    if fill:
        tex = _colour_fill(dev, tex, mask == 1, have_tile, rows, W, tile, int(fill_rounds or 2 * tile))
    out = dr.zeros(U8, rows * W * 3)
    q = dr.arange(U, rows * W) * 3
    for c in range(3):
        dr.scatter(out, U8(dr.clip(dr.round(tex[c]), 0.0, 255.0)), q + c)
    texture = dev.to_host(out).reshape(rows, W, 3)
    mask_host = dev.to_host(mask, np.int8).reshape(rows, W)
    return texture, mask_host, counts, layout, relocated


def _colour_fill(dev, tex, have, have_tile, rows: int, width: int, tile: int, rounds: int):
    """:func:`methods.layered_pvs.packing.colour_fill`'s rounds on the float32 planes ``tex`` (``have``: the texels
    that hold a fragment), a lane per tile that holds a fragment and an empty texel: the tile in local memory, its
    rounds as symbolic loops over its texels in the numba pass's order (sums of the have-neighbours up, down, left,
    right in float32)."""
    dr, I32, U, F32 = dev.dr, dev.Int32, dev.UInt32, dev.Float
    t2 = tile * tile
    bx_count = width // tile
    q = dr.arange(U, rows * width)
    tile_of = (q // width // tile) * bx_count + (q % width) // tile
    empty_tile = dr.zeros(dev.Bool, (rows // tile) * bx_count)
    dr.scatter(empty_tile, True, tile_of, ~have)
    work = dr.compress(have_tile & empty_tile)
    n = dr.width(work)
    if n == 0:
        return tex
    corner = U(work // bx_count) * (tile * width) + U(work % bx_count) * tile

    def address(i):
        return corner + (i // tile) * width + i % tile

    col = [dr.alloc_local(F32, t2) for _ in range(3)]
    avg = [dr.alloc_local(F32, t2) for _ in range(3)]
    got, new = dr.alloc_local(I32, t2), dr.alloc_local(I32, t2)

    def load(i, r, g, b, got):
        for loc, plane in zip((r, g, b), tex):
            loc[i] = dr.gather(F32, plane, address(i))
        got[i] = I32(dr.gather(dev.Bool, have, address(i)))
        return r, g, b, got

    col[0], col[1], col[2], got = _block_loop(dev, n, t2, load, *col, got)

    def grow(i, grew, r, g, b, ar, ag, ab, got, new):
        sums = [dr.zeros(F32, n) for _ in range(3)]
        count = dr.zeros(F32, n)
        for dy, dx in _NEIGHBOURS:
            inside, j = _neighbour(dev, i, tile, dy, dx)
            ok = inside & (got[j] != 0)
            sums = [dr.select(ok, sc + loc[j], sc) for sc, loc in zip(sums, (r, g, b))]
            count = dr.select(ok, count + 1.0, count)
        fresh = (got[i] == 0) & (count > 0)
        new[i] = I32(fresh)
        for loc, sc in zip((ar, ag, ab), sums):
            loc[i] = sc / dr.maximum(count, 1.0)
        return grew | fresh, r, g, b, ar, ag, ab, got, new

    def apply(i, r, g, b, ar, ag, ab, got, new):
        fresh = new[i] != 0
        for loc, a in zip((r, g, b), (ar, ag, ab)):
            loc[i] = dr.select(fresh, a[i], loc[i])
        got[i] = dr.select(fresh, 1, got[i])
        return r, g, b, ar, ag, ab, got, new

    def round_(k, go, *st):
        grew, *st = _block_loop(dev, n, t2, grow, dr.zeros(dev.Bool, n), *st)
        st = _block_loop(dev, n, t2, apply, *st)
        return (k + 1, grew) + tuple(st)

    out = dr.while_loop((dr.zeros(I32, n), dr.full(dev.Bool, True, n), *col, *avg, got, new),
                        lambda k, go, *_: go & (k < rounds), round_)
    col = out[2:5]

    def store(i, r, g, b):
        for loc, plane in zip((r, g, b), tex):
            dr.scatter(plane, loc[i], address(i))
        return r, g, b

    _block_loop(dev, n, t2, store, *col)
    dr.eval(*tex)
    return tex


# ------------------------------------------------------------------------------------------ path tracing

class DeviceLights:
    """:class:`methods.layered_pvs.server.LightSampler`'s lights on the device (float64): the choice's power and
    centres (a point light's position, a triangle's centroid), its power CDF, and the point and triangle lights'
    sampling data."""

    def __init__(self, dev, lights):
        up = dev.to_device
        F64, V3 = dev.Float64, dev.Vector3d
        self.count, self.n_point = len(lights.power), int(lights.n_point)
        self.per_point = self.count <= lights.PER_POINT_LIGHTS
        self.min_d2 = float(lights.min_d2)
        self.power, self.centres = up(lights.power, F64), up(lights.centres, V3)
        self.cdf, self.pmf = up(lights.cdf, F64), up(lights.pmf, F64)
        self.cdf_last = float(lights.cdf[-1]) if self.count else 0.0
        pad = lambda a, k: a if len(a) else np.zeros((1, k))  # noqa: E731  (a gather needs a table of one row)
        self.point_pos, self.point_int = up(pad(lights.point_pos, 3), V3), up(pad(lights.point_int, 3), V3)
        tri = lights.tri.reshape(-1, 9)
        self.tri = [up(pad(tri[:, 3 * k:3 * k + 3], 3), V3) for k in range(3)]
        self.tri_n, self.tri_l = up(pad(lights.tri_n, 3), V3), up(pad(lights.tri_l, 3), V3)
        self.tri_area = up(lights.tri_area if len(lights.tri_area) else np.zeros(1), F64)
        self.n_tri = len(lights.tri_area)
        # A few lights: their data as scalars the kernel broadcasts, and the loops over them written out (per-lane
        # gathers of float64 cost on llvm_ad_rgb about as much as the shading they feed).
        self.unrolled = self.per_point and self.count <= UNROLL_LIGHTS
        if self.unrolled:
            ops = dev.opaques
            self.s_power = ops(lights.power)
            self.s_centres = [ops(c) for c in lights.centres]
            self.s_point_pos = [ops(c) for c in lights.point_pos]
            self.s_point_int = [ops(c) for c in lights.point_int]


def _choose_light(dev, lt: DeviceLights, p, u_sel):
    """(light index UInt32, selection probability Float64) per lane, as ``LightSampler.choose``: in proportion to the
    irradiance bound ``power / max(d^2, min_d2)`` at the point (the total, then the first light whose running sum
    reaches ``u * total``: written out over broadcast scalars for a few lights, :attr:`DeviceLights.unrolled`, else
    two symbolic loops over a light table), or, with more than ``PER_POINT_LIGHTS`` lights, to power (a binary
    search of the CDF)."""
    dr, F64, U = dev.dr, dev.Float64, dev.UInt32
    n = dr.width(u_sel)
    last = lt.count - 1
    if not lt.per_point:
        x = u_sel * dev.opaque(F64, lt.cdf_last)
        j = dr.minimum(U(dr.binary_search(0, last, lambda i: dr.gather(F64, lt.cdf, i) <= x)), last)
        return j, dr.gather(F64, lt.pmf, j)
    min_d2 = dev.opaque(F64, lt.min_d2)
    if lt.unrolled:
        ws, tot = [], None
        for li in range(lt.count):
            c = lt.s_centres[li]
            dx, dy, dz = p.x - c[0], p.y - c[1], p.z - c[2]
            ws.append(lt.s_power[li] / dr.maximum((dx * dx + dy * dy) + dz * dz, min_d2))
            tot = ws[-1] if tot is None else tot + ws[-1]
        x = u_sel * tot
        acc, j, w_j, found = None, dr.full(U, last, n), ws[-1], dr.zeros(dev.Bool, n)
        for li in range(lt.count):
            acc = ws[li] if acc is None else acc + ws[li]
            hit = ~found & (acc >= x)
            j, w_j, found = dr.select(hit, U(li), j), dr.select(hit, ws[li], w_j), found | hit
        return j, w_j / dr.maximum(tot, 1e-300)
    count = dev.opaque(U, lt.count)

    def weight(li):
        c = dr.gather(dev.Vector3d, lt.centres, li)
        d = p - c
        return dr.gather(F64, lt.power, li) / dr.maximum((d.x * d.x + d.y * d.y) + d.z * d.z, min_d2)

    li, tot = dr.zeros(U, n), dr.zeros(F64, n)
    li, tot = dr.while_loop((li, tot), lambda li, tot: li < count, lambda li, tot: (li + 1, tot + weight(li)))
    x = u_sel * tot
    li, acc, j, found = dr.zeros(U, n), dr.zeros(F64, n), dr.full(U, last, n), dr.zeros(dev.Bool, n)

    def body(li, acc, j, found):
        acc = acc + weight(li)
        hit = acc >= x
        return li + 1, acc, dr.select(hit, li, j), hit

    li, acc, j, found = dr.while_loop((li, acc, j, found), lambda li, acc, j, found: (li < count) & ~found, body)
    return j, weight(j) / dr.maximum(tot, 1e-300)


def _cosine_hemisphere(dev, n, u0, u1):
    """A cosine-weighted direction (Vector3f) about the unit normal ``n`` (``server._cosine_hemisphere``'s frame), in
    float32: the ray is traced in float32 anyway, and float64 sine and cosine are software routines on both
    backends."""
    dr, F = dev.dr, dev.Float
    r = dr.sqrt(u0)
    s, c = dr.sincos(2 * math.pi * u1)
    lx, ly, lz = r * c, r * s, dr.sqrt(dr.maximum(0.0, 1.0 - u0))
    n = dev.Vector3f(n)
    side = dr.abs(n.x) > 0.9
    a = dev.Vector3f(dr.select(side, 0.0, 1.0), dr.select(side, 1.0, 0.0), F(0.0))
    t = dr.normalize(dr.cross(n, a))
    b = dr.cross(n, t)
    return dr.normalize(t * lx + b * ly + n * lz)


def _light_sample(dev, lt: DeviceLights, p, j, pmf, is_point, u4, u5):
    """(target point, weight L cos_y / (d^2 pdf) or I / (d^2 pdf), valid) per lane for light ``j`` chosen with
    probability ``pmf`` (``LightSampler.sample``): a point light's position, or a uniform point on a triangle light
    (``sqrt`` warp of ``u4``, ``u5``) that must face the point. The kinds a scene lacks are left out of the kernel."""
    dr, F64, U = dev.dr, dev.Float64, dev.UInt32
    zero = U(0)
    y = w = None
    good = dr.full(dev.Bool, True, dr.width(pmf))
    if lt.n_point:
        if lt.unrolled:  # a select over the few lights' broadcast scalars instead of two gathers per lane
            y_pt = dev.Vector3d(*lt.s_point_pos[0])
            inten = dev.Vector3d(*lt.s_point_int[0])
            for li in range(1, lt.n_point):
                here = j == li
                y_pt = dr.select(here, dev.Vector3d(*lt.s_point_pos[li]), y_pt)
                inten = dr.select(here, dev.Vector3d(*lt.s_point_int[li]), inten)
        else:
            jp = dr.select(is_point, j, zero)
            y_pt = dr.gather(dev.Vector3d, lt.point_pos, jp, is_point)
            inten = dr.gather(dev.Vector3d, lt.point_int, jp, is_point)
        e = y_pt - p
        d2 = dr.maximum((e.x * e.x + e.y * e.y) + e.z * e.z, 1e-12)
        y, w = y_pt, inten / d2 / pmf
    if lt.n_tri:
        on_tri = ~is_point
        jt = dr.select(is_point, zero, j - lt.n_point)
        su = dr.sqrt(u4)
        b1, b2 = 1.0 - su, u5 * su
        t0 = dr.gather(dev.Vector3d, lt.tri[0], jt, on_tri)
        y_tri = (t0 + b1 * (dr.gather(dev.Vector3d, lt.tri[1], jt, on_tri) - t0)) \
            + b2 * (dr.gather(dev.Vector3d, lt.tri[2], jt, on_tri) - t0)
        e = y_tri - p
        d2t = dr.maximum((e.x * e.x + e.y * e.y) + e.z * e.z, 1e-12)
        cos_y = -dr.dot(e / dr.sqrt(d2t), dr.gather(dev.Vector3d, lt.tri_n, jt, on_tri))
        w_tri = dr.gather(dev.Vector3d, lt.tri_l, jt, on_tri) \
            * (cos_y * dr.gather(F64, lt.tri_area, jt, on_tri) / d2t / pmf)
        good = is_point | (cos_y > 0.0)
        y = y_tri if y is None else dr.select(is_point, y, y_tri)
        w = w_tri if w is None else dr.select(is_point, w, w_tri)
    return y, w, good


def path_samples(dev, frag, lights, spp: int, max_depth: int, rr_depth: int, seed: int, position=None):
    """The indirect part of the layered path tracer (``server.path_trace``, §4.4) on the device: ``spp`` paths per
    fragment (lane ``k * n + i`` is sample ``k`` of fragment ``i``), cosine-weighted Lambertian bounces, Russian
    roulette from vertex ``rr_depth`` on, and next-event estimation towards one light at every later vertex (chosen
    as ``LightSampler`` chooses it). The same estimator and the same counter-based random numbers as the host passes
    (:mod:`methods.layered_pvs.kernels`; the PCG hash of lane and draw, ``server._path_numbers``), so the two agree to
    rounding path by path (the bounce direction is made in float32 here; a last-bit difference rarely sends a path
    elsewhere).

    Returns the (n * spp) float64 path contributions (Vector3d, evaluated: demodulated, the primary fragment's albedo
    left out, its direct light not included); the fragments go up once (``position``: their positions already on
    the device, :func:`fragment_gbuffer`'s). Each bounce is one kernel (its
    closest-hit query, the hit's attributes, the light's choice and sample, the shadow query); the lanes stay in
    place (masked) from bounce to bounce. Its queries' rays are recorded under ``"path_trace"`` (:func:`recording`)."""
    from suite.core.device.gbuffer import hit_surface
    from suite.core.shading import SHADOW_TMAX_SCALE
    from suite.core.trace.base import MAX_RAY_LENGTH

    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    tracer = dev.tracer
    n = len(frag.position)
    total = n * int(spp)
    if total == 0 or max_depth < 3 or len(lights.power) == 0:
        return dr.zeros(dev.Vector3d, total)
    lt = DeviceLights(dev, lights)
    lane = dev.arange(total)
    fi = lane % dev.opaque(U, n)
    if position is None:
        position = dev.to_device(np.asarray(frag.position, np.float64), dev.Point3d)
    p = dr.gather(dev.Point3d, position, fi)
    made = twins(frag, dev)  # the normals where this device made the fragments, else uploaded
    if made is not None:
        ng_all, ns_all = made.geo_normal, made.normal
    else:
        ng_all, ns_all = (dev.to_device(np.asarray(a, np.float64), dev.Vector3d) for a in (frag.geo_normal,
                                                                                            frag.normal))
    ng, ns = dr.gather(dev.Vector3d, ng_all, fi), dr.gather(dev.Vector3d, ns_all, fi)
    thr = dr.full(dev.Vector3d, 1.0, total)
    sample = dr.zeros(dev.Vector3d, total)
    live = dr.full(dev.Bool, True, total)
    closest_rays = dr.zeros(U, total)   # closest-hit queries per lane (the alpha walk's included)
    shadow_rays = dr.zeros(U, total)
    # the host passes' numbers (server._path_numbers): the PCG hash of (lane, seed) and the draw's dimension
    key = device_rng.lane_keys(dev, lane, dev.opaque(U, int(pcg_np(int(seed) & 0xFFFFFFFF))))
    length = dr.full(F, float(MAX_RAY_LENGTH), total)
    one, zero = U(1), U(0)
    depth = 1
    while depth + 1 < max_depth:
        dims = dim_hashes(8 * depth + np.arange(6))
        u = [device_rng.uniform(dev, key, dev.opaque(U, int(h))) for h in dims]
        # Russian roulette, then a cosine-weighted bounce (its pdf cancels cos/pi; the albedo remains).
        if depth >= rr_depth:
            q = dr.minimum(dr.maximum(dr.maximum(thr.x, thr.y), thr.z), 0.95)
            live = live & (F64(u[0]) < q)
            thr = thr / dr.maximum(q, 1e-12)
        d32 = _cosine_hemisphere(dev, ns, F(u[1]), F(u[2]))  # 24-bit numbers: exact in float32
        d64 = dev.Vector3d(d32)
        queried = live & (dr.dot(d64, ng) > 0.0)
        o64 = dev.offset_origin(p, ng)
        o_local = dev.local_f32(o64)
        _, prim, hu, hv, traced = dev.closest(o_local, d32, length, queried)
        closest_rays = closest_rays + (dr.select(queried, one, zero) if traced is None else traced)
        live = queried & (prim >= 0)
        hit = hit_surface(dev, prim, hu, hv, live, o64, d64, d64)
        depth += 1
        p, ng, ns = hit.position, hit.ng, hit.ns
        thr = thr * dev.Vector3d(hit.albedo)
        # Next-event estimation towards one light (LightSampler.sample): a point light's intensity over d^2, or a
        # uniform point on a triangle light with its cosine and area; both over the choice's probability.
        j, pmf = _choose_light(dev, lt, p, F64(u[3]))
        is_point = j < lt.n_point
        y, w, good = _light_sample(dev, lt, p, j, pmf, is_point, F64(u[4]), F64(u[5]))
        e = y - p
        dist = dr.sqrt((e.x * e.x + e.y * e.y) + e.z * e.z)
        wi = e / dr.maximum(dist, 1e-30)
        cos_x = dr.dot(wi, ns)
        shadow = live & good & (cos_x > 0.0)
        # from the light's side of the surface, short of the light
        so64 = dev.offset_origin(p, dr.select(dr.dot(wi, ng) >= 0.0, ng, -ng))
        seg = dr.norm((p + wi * dist) - so64)
        so_local, sd32, slen = dev.local_f32(so64), dev.Vector3f(wi), F(seg * SHADOW_TMAX_SCALE)
        blocked, straced = dev.occluded_rays(so_local, sd32, slen, shadow)
        sample = sample + dr.select(shadow & ~blocked, thr * w * (cos_x * (1.0 / math.pi)), 0.0)
        shadow_rays = shadow_rays + dr.select(shadow, one, zero)
        if straced is not None:
            closest_rays = closest_rays + straced
        dr.eval(p, ng, ns, thr, live, sample, closest_rays, shadow_rays)
        _record(dev, "path_trace", "i", queried, o_local, d32, length)
        _record(dev, "path_trace", "o", shadow, so_local, sd32, slen)
    dev.sync()
    bound = (max_depth + 1) * (1 + MAX_ALPHA_LAYERS) * 2
    tracer.counters["rays_intersect"] += dev.sum_u32(closest_rays, bound)
    tracer.counters["rays_occluded"] += dev.sum_u32(shadow_rays, max_depth + 1)
    return sample


def path_trace(dev, frag, lights, spp: int, max_depth: int, rr_depth: int, seed: int) -> np.ndarray:
    """:func:`path_samples` copied to the host: (n * spp, 3) float64."""
    return dev.to_host(path_samples(dev, frag, lights, spp, max_depth, rr_depth, seed), np.float64)


def fragments(dev, layers, origins64: np.ndarray | None, dirs64: np.ndarray | None, t_s: float, view=None):
    """``server.fragments`` on the device, with its bits on ``llvm_ad_rgb``: the layer samples' triangles and
    barycentrics and their pixels' rays go up, :func:`suite.core.device.gbuffer.hit_surface` makes the surfaces
    (``surface_attributes``' float64 operations, the normals turned towards the ray as ``_face_fragments`` turns them),
    emission is kept on front faces, and the fields come back in one evaluation. The position and the normals stay on
    the device as well (``Fragments.device``), for :func:`fragment_gbuffer`. ``view`` (``origins64`` and ``dirs64``
    None): the layer view's rays, made on the device (:func:`view_rays`); the fragments' directions come back."""
    from methods.layered_pvs.server import Fragments
    from suite.core.device.gbuffer import hit_surface

    dr = dev.dr
    dev.tracer.update(t_s)  # the device's vertex tables at the update's time
    # flat indices (three times faster than np.nonzero and (k, y, x) fancy indexing), in np.nonzero's order
    shape = layers.prim.shape
    flat = np.flatnonzero(layers.valid)
    k, y, x = np.unravel_index(flat, shape)
    n = len(flat)
    pix = flat % (shape[1] * shape[2])
    if n == 0:
        z64, z32 = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
        return Fragments((k, y, x), z64, z64.copy(), z64.copy(), z32, z32.copy(), z64.copy())
    prim = dev.to_device(np.asarray(layers.prim).reshape(-1)[flat].astype(np.int32), dev.Int32)
    u = dev.to_device(np.asarray(layers.u, np.float32).reshape(-1)[flat], dev.Float)
    v = dev.to_device(np.asarray(layers.v, np.float32).reshape(-1)[flat], dev.Float)
    if view is not None:
        pix_d = dev.to_device(pix.astype(np.uint32), dev.UInt32)
        d = dr.gather(dev.Vector3d, view_rays(dev, view)[0], pix_d)
        o = dev.Point3d(*dev.opaques([float(x) for x in view.pose.position]))  # from memory: no kernel per pose
        view_dir = None  # comes back with the surfaces
    else:
        view_dir = np.take(np.ascontiguousarray(dirs64, np.float64), pix, axis=0)
        o = dev.to_device(np.take(np.ascontiguousarray(origins64, np.float64), pix, axis=0), dev.Point3d)
        d = dev.to_device(view_dir, dev.Vector3d)
    valid = dr.full(dev.Bool, True, n)
    hit = hit_surface(dev, prim, u, v, valid, o, d, d)
    tables = dev.tables
    emission = tables.front_emission(hit.mat, hit.front)
    fields = [hit.position, hit.ng, hit.ns, hit.albedo, emission] + ([d] if view_dir is None else [])
    # the twins evaluated in the kernel that makes the copies (else the path tracer's first read computes them again)
    host = dev.to_host_all(fields, [np.float64, np.float64, np.float64, np.float32, np.float32, np.float64],
                           keep=(hit.position, hit.ng, hit.ns))
    twins = SimpleNamespace(dev=dev, position=hit.position, geo_normal=hit.ng, normal=hit.ns)
    return Fragments((k, y, x), *host[:5], host[5] if view_dir is None else view_dir, device=twins)


def twins(frag, dev):
    """The fragments' device twins (``Fragments.device``) where ``dev`` made them, else None."""
    made = getattr(frag, "device", None)
    return made if made is not None and made.dev is dev else None


def fragment_gbuffer(dev, frag):
    """The fragments as a (1 x N) :class:`~suite.core.device.gbuffer.DeviceGBuffer` of albedo 1 without emission
    (``server._fragment_gbuffer`` on the device): float64 positions, the normals rounded to float32 as the G-buffer
    keeps them (from the fragments' device twins where :func:`fragments` made them, else uploaded)."""
    from suite.core.device.gbuffer import DeviceGBuffer

    dr = dev.dr
    n = len(frag.position)
    zeros = dr.zeros(dev.Float, n)
    made = twins(frag, dev)
    if made is not None:
        position, normal, geo_normal = made.position, dev.Vector3f(made.normal), dev.Vector3f(made.geo_normal)
    else:
        position = dev.to_device(np.asarray(frag.position, np.float64), dev.Point3d)
        normal = dev.to_device(np.asarray(frag.normal, np.float32), dev.Vector3f)
        geo_normal = dev.to_device(np.asarray(frag.geo_normal, np.float32), dev.Vector3f)
    g = DeviceGBuffer(device=dev, width=n, height=1, t_s=float("nan"), camera_position=np.zeros(3, np.float32),
                      position=position, normal=normal, geo_normal=geo_normal,
                      albedo=dr.full(dev.Vector3f, 1.0, n), emission=None, depth=zeros, prim=dr.zeros(dev.Int32, n),
                      valid=dr.full(dev.Bool, True, n), view_dir=None, material=dr.zeros(dev.Int32, n), kind=None,
                      u=zeros, v=zeros)
    dr.eval(*g.fields())
    return g


def direct_light(dev, scene, frag, t_s: float, area_samples: int, seed: int, g=None):
    """``server.direct_illumination`` on the device: the suite's direct-lighting kernels
    (:func:`suite.core.shading.compose_direct` with :mod:`suite.core.device.shading`: every point light with its own
    shadow ray, area lights with ``area_samples`` stratified samples and counter-based random numbers) on
    :func:`fragment_gbuffer` (``g``, made here when not given). Returns the demodulated light per fragment
    (Vector3d, on the device)."""
    from suite.core import shading
    from suite.core.device import shading as device_shading

    g = fragment_gbuffer(dev, frag) if g is None else g
    kernels = device_shading
    if _RECORDS is not None:  # the shadow rays of both kinds of light, for the benchmark's raw replay
        rays = _RECORDS.setdefault("path_trace", [])
        rays += [("o", ray) for ray, _ in device_shading.shadow_rays(g, scene.lights_at(t_s), dev.tracer)]
        kernels = SimpleNamespace(point_light_visibility=device_shading.point_light_visibility,
                                  shade_point_lights=device_shading.shade_point_lights,
                                  area_light_radiance=partial(device_shading.area_light_radiance, record=rays))
    return dev.Vector3d(shading.compose_direct(kernels, scene, g, dev.tracer, t_s, area_samples, seed).rgb)


def path_moments(dev, sample, direct, n: int, spp: int):
    """(mean illumination float32 (N, 3), first and second moments of its luminance (N,)) per fragment, each of its
    ``spp`` samples (lanes ``k * n + i`` of ``sample``) with its direct light added, in sample order
    (``kernels._path_moments``' operations; copied to the host once)."""
    dr, F64 = dev.dr, dev.Float64
    illum = m1 = m2 = None
    for k in range(int(spp)):
        # the offset from memory: the fragment count changes every update, and a literal would compile anew
        x = dr.gather(dev.Vector3d, sample, dev.arange(n) + dev.opaque(dev.UInt32, k * n)) + direct
        lum = (x.x * 0.2126 + x.y * 0.7152) + x.z * 0.0722
        if illum is None:
            illum, m1, m2 = x, lum, lum * lum
        else:
            illum, m1, m2 = illum + x, m1 + lum, m2 + lum * lum
    illum = dev.Vector3f(illum / F64(spp))
    m1, m2 = m1 / F64(spp), m2 / F64(spp)
    dr.eval(illum, m1, m2)
    return dev.to_host(illum, np.float32), dev.to_host(m1, np.float64), dev.to_host(m2, np.float64)


# ------------------------------------------------------------------------------------------ PVS and depth peeling

_RECORDS: dict | None = None   # stage -> [("i" | "o", Ray3f)] while a benchmark records (see recording)


@contextmanager
def recording(records: dict):
    """While active, the device passes put the rays of each of their queries (compacted to the lanes traced,
    evaluated) into ``records[stage]`` (``"pvs"``, ``"layers"``, ``"path_trace"``): the benchmark's raw replay."""
    global _RECORDS
    outer, _RECORDS = _RECORDS, records
    try:
        yield records
    finally:
        _RECORDS = outer


def _record(dev, stage: str, kind: str, active, o_local, d, length) -> None:
    """A query's rays (the lanes where ``active`` holds; every lane where it is None) into the records of ``stage``."""
    if _RECORDS is None:
        return
    ray = dev.raw_ray(o_local, d, length) if active is None else dev.compacted_ray(active, o_local, d, length)
    _RECORDS.setdefault(stage, []).append((kind, ray))


def compute_pvs(dev, views, fov_deg: float, width: int, height: int) -> np.ndarray:
    """Algorithm 1 on the device: for each (distinct) view an id buffer by ray casting against the whole scene
    (:func:`suite.core.device.gbuffer.camera_rays`, the host's pixel-centre rays to the bit, and the tracing-frame
    origin as the host's ``local_rays`` rounds it), the hit triangles marked in a per-face table; the marks come
    back once, as sorted ids (``server.compute_pvs``'s ids on ``llvm_ad_rgb``)."""
    from suite.core.device.gbuffer import camera_rays
    from suite.core.trace.base import MAX_RAY_LENGTH

    dr, F, U = dev.dr, dev.Float, dev.UInt32
    tracer = dev.tracer
    n = int(width) * int(height)
    marks = dr.zeros(U, tracer.scene.num_faces)
    length = dr.full(F, float(MAX_RAY_LENGTH), n)
    traced_total = 0
    for pose in views:
        d64, _, _ = camera_rays(dev, pose, fov_deg, width, height)
        d32 = dev.Vector3f(d64)
        o_local = _origin_local(dev, pose.position)
        _, prim, _, _, traced = dev.closest(o_local, d32, length)
        dr.scatter(marks, U(1), U(dr.maximum(prim, 0)), prim >= 0)
        dr.eval(marks, *([traced] if traced is not None else []))
        traced_total += n if traced is None else dev.sum_u32(traced, 1 + MAX_ALPHA_LAYERS)
        _record(dev, "pvs", "i", None, o_local, d32, length)
    tracer.counters["rays_intersect"] += traced_total
    return np.nonzero(dev.to_host(marks))[0].astype(np.int64)


def _origin_local(dev, position):
    """A camera at ``position`` as every pixel's tracing-frame origin, rounded as the host path rounds it: the
    float32 world point (``camera_rays(dtype=float32)``), then ``float32(float64(o) - shift)`` (``as_rays``). One
    value per coordinate, read from memory (broadcast against the pixels' directions): as literals, every new camera
    position would compile new PVS, peeling and fragment kernels (20-130 ms each on llvm_ad_rgb)."""
    o32 = np.asarray(position, np.float64).astype(np.float32)
    local = (o32.astype(np.float64) - np.asarray(dev.tracer.shift, np.float64)).astype(np.float32)
    return dev.Point3f(*[dev.Float(v) for v in dev.opaques([float(x) for x in local])])  # float32 values: exact


def _past(dev, t):
    """``server.past`` on the device: ``t * (1 + PEEL_REL_EPS)`` in float32, then the next float32 up (the bit
    pattern plus one: distances are finite and not negative)."""
    from methods.layered_pvs.server import PEEL_REL_EPS

    dr = dev.dr
    scaled = t * dev.opaque(dev.Float, float(np.float32(1 + PEEL_REL_EPS)))
    return dr.reinterpret_array(dev.Float, dr.reinterpret_array(dev.UInt32, scaled) + 1)


def view_rays(dev, view):
    """The layer view's pixel-centre rays made on the device (``server.view_rays``' bits): the float64 directions
    (:func:`suite.core.device.gbuffer.camera_rays`), and the float32 tracing-frame rays the peeling traces, the
    origin rounded as the host path rounds ``view_rays``' origins (float32 world point, then the frame shift)."""
    from suite.core.device.gbuffer import camera_rays

    d64, _, _ = camera_rays(dev, view.pose, view.fov_deg, int(view.width), int(view.height))
    return d64, _origin_local(dev, view.pose.position), dev.Vector3f(d64)


def peel(dev, origins: np.ndarray | None, dirs: np.ndarray | None, layers: int, keep_mask, max_skips: int = 256,
         wavefront: bool | None = None, view=None):
    """Ray-traced depth peeling (§4.1.2) on the device, the layers of ``server.peel`` (its queries and their bits on
    ``llvm_ad_rgb``): each ray traced from just past its previous hit (the float32 ``past``; origin advanced by
    ``float32(d * start)`` in float32 as ``as_rays`` advances it), a hit on a triangle outside ``keep_mask`` (bool per
    face; None keeps every hit) stepped over and traced again (at most ``max_skips`` queries per layer), a kept hit
    stored as the ray's next layer. The rays go up once; the layers come back once. Returns (t, prim, u, v) as
    (layers, N) host arrays (inf / -1 / 0 where empty).

    Two schedules give the same queries and bits. The default is one kernel: a loop per ray over its queries, every
    layer and step-over of the ray in turn (no host round trip between queries; a packet keeps tracing while one of
    its rays still has layers to find). ``wavefront`` (and every call while :func:`recording` is active, whose raw
    replay needs each query's rays) runs one query per kernel over the rays still going, compacted between queries
    (one host synchronisation and Python-traced kernel per query: at 480x270 with a PVS of a third of the faces, ten
    queries of 3 to 168 k rays).

    ``view`` (a ``server.LayerView``, with ``origins`` and ``dirs`` None): the view's pixel-centre rays, made on the
    device (:func:`view_rays`) instead of going up."""
    from suite.core.trace.base import MAX_RAY_LENGTH

    dr, F, F64, U, I = dev.dr, dev.Float, dev.Float64, dev.UInt32, dev.Int32
    tracer = dev.tracer
    if view is not None:
        _, o_all, d_all = view_rays(dev, view)
        n = dr.width(d_all)
    else:
        n = len(dirs)
        shift = np.asarray(tracer.shift, np.float64)
        o_loc = (np.asarray(origins, np.float32).astype(np.float64) - shift).astype(np.float32)
        o_all = dev.to_device(o_loc, dev.Point3f)
        d_all = dev.to_device(np.asarray(dirs, np.float32), dev.Vector3f)
    use_keep = keep_mask is not None
    keep = dev.to_device(np.asarray(keep_mask, np.uint32), U) if use_keep else None
    t_out = dr.full(F, float("inf"), layers * n)
    p_out = dr.full(I, -1, layers * n)
    u_out, v_out = dr.zeros(F, layers * n), dr.zeros(F, layers * n)
    max_length = float(MAX_RAY_LENGTH)
    if wavefront is None:
        wavefront = _RECORDS is not None
    if not wavefront:
        queries = _peel_loop(dev, o_all, d_all, keep, layers, max_skips, (t_out, p_out, u_out, v_out))
        tracer.counters["rays_intersect"] += int(queries)
        host = dev.to_host_all([t_out, p_out, u_out, v_out])
        return tuple(a.reshape(layers, n) for a in (host[0], host[1].astype(np.int64), host[2], host[3]))
    idx, start = dev.arange(n), dr.zeros(F, n)
    queries = 0
    for k in range(layers):
        base = dev.opaque(U, k * n)
        for _ in range(max_skips):
            if dr.width(idx) == 0:
                break
            d = dr.gather(dev.Vector3f, d_all, idx)
            o0 = o_all if dr.width(o_all) == 1 else dr.gather(dev.Point3f, o_all, idx)  # one origin: the view's
            o_local = dev.Point3f(*[o0[c] + F(d[c] * start) for c in range(3)])
            length = dr.minimum(dr.maximum(F(F64(max_length) - F64(start)), 0.0), max_length)
            t, prim, u, v, traced = dev.closest(o_local, d, length)
            ti = t + start
            hit = prim >= 0
            kept = hit & (dr.gather(U, keep, U(dr.maximum(prim, 0)), hit) != 0) if use_keep else hit
            slot = base + idx
            for out, value in ((t_out, ti), (p_out, prim), (u_out, u), (v_out, v)):
                dr.scatter(out, value, slot, kept)
            skip = hit & ~kept
            dr.eval(t_out, p_out, u_out, v_out, ti, skip, *([traced] if traced is not None else []))
            queries += dr.width(idx) if traced is None else dev.sum_u32(traced, 1 + MAX_ALPHA_LAYERS)
            _record(dev, "layers", "i", None, o_local, d, length)
            sel = dr.compress(skip)
            if dr.width(sel) == 0:  # (an empty array does not broadcast against a scalar)
                break
            idx, start = dr.gather(U, idx, sel), _past(dev, dr.gather(F, ti, sel))
            dr.eval(idx, start)
        if k + 1 == layers:
            break
        # the next layer: every pixel with a fragment in this one, from just past it
        idx = dr.compress(dr.gather(I, p_out, base + dev.arange(n)) >= 0)
        if dr.width(idx) == 0:
            break
        start = _past(dev, dr.gather(F, t_out, base + idx))
        dr.eval(idx, start)
    tracer.counters["rays_intersect"] += int(queries)
    host = [dev.to_host(a).reshape(layers, n) for a in (t_out, p_out, u_out, v_out)]
    return host[0], host[1].astype(np.int64), host[2], host[3]


def _peel_loop(dev, o_all, d_all, keep, layers: int, max_skips: int, out) -> int:
    """:func:`peel`'s queries as one kernel (its default schedule): per ray a loop whose iterations are the ray's
    queries in the wavefront schedule's order, with the same operations, so the same layers. A query's kept hit is
    the ray's next layer (the ray goes on from just past it while layers remain), a hit outside the PVS is stepped
    over (at most ``max_skips`` queries per layer), a miss ends the ray. Writes the layers into ``out`` (t, prim,
    u, v; layer-major) and returns the backend queries made."""
    from suite.core.trace.base import MAX_RAY_LENGTH

    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    t_out, p_out, u_out, v_out = out
    n = dr.width(d_all)
    max_length = float(MAX_RAY_LENGTH)
    idx = dev.arange(n)
    n_mem = dev.opaque(U, n)  # the layer stride, from memory: a literal would bake the ray count into the kernel

    def body(k, tries, start, alive, queries):
        o_local = dev.Point3f(*[o_all[c] + F(d_all[c] * start) for c in range(3)])
        length = dr.minimum(dr.maximum(F(F64(max_length) - F64(start)), 0.0), max_length)
        t, prim, u, v, traced = dev.closest(o_local, d_all, length, alive)
        ti = t + start
        hit = alive & (prim >= 0)
        kept = hit & (dr.gather(U, keep, U(dr.maximum(prim, 0)), hit) != 0) if keep is not None else hit
        slot = k * n_mem + idx
        for buf, value in ((t_out, ti), (p_out, prim), (u_out, u), (v_out, v)):
            dr.scatter(buf, value, slot, kept)
        queries = queries + (dr.select(alive, U(1), U(0)) if traced is None else dr.select(alive, traced, U(0)))
        skip = hit & ~kept
        tries = tries + 1
        go_on = (kept & (k + 1 < layers)) | (skip & (tries < max_skips))
        start = dr.select(hit, _past(dev, ti), start)
        tries = dr.select(kept, U(0), tries)
        k = dr.select(kept, k + 1, k)
        return k, tries, start, go_on, queries

    state = (dr.zeros(U, n), dr.zeros(U, n), dr.zeros(F, n), dr.full(dev.Bool, True, n), dr.zeros(U, n))
    _, _, _, _, queries = dr.while_loop(state, lambda k, tries, start, alive, q: alive, body)
    dev.eval(t_out, p_out, u_out, v_out, queries)
    return dev.sum_u32(queries, layers * max_skips * (1 + MAX_ALPHA_LAYERS))
