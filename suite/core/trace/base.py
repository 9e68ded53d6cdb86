"""The tracing interface shared by all backends.

Every backend answers two queries on numpy arrays of float32 rays:

* ``intersect(origins, dirs, tmin, tmax) -> Hits``: closest hit (t, global face index, barycentrics u, v),
  with ``t = inf`` and ``prim = -1`` on a miss. Hit point = (1-u-v)·p0 + u·p1 + v·p2 of ``scene.faces[prim]``.
* ``occluded(origins, dirs, tmin, tmax) -> bool``: any hit with tmin < t < tmax (shadow rays).

``tmin`` and ``tmax`` may be scalars or per-ray arrays. Neither backend supports a per-ray ``tmin`` natively
(embreex fixes ``tnear`` at 0), so the origin is advanced by ``tmin`` along the ray and ``t`` is shifted back.
Robust shadow-ray origins are the caller's job (see :func:`suite.core.trace.robust.offset_ray_origin`).

Backends trace in a frame centred on the scene's bounding box: geometry and ray origins are shifted by the
box centre in float64 before they become float32. A scene far from the origin then gets the precision of a
scene at the origin inside the backend (hit distances, watertight edge tests); only its input coordinates
carry their own rounding.

A tracer reuses its ray buffers from query to query, so one tracer serves one thread at a time. Rays already in
the tracing frame (made by :func:`as_rays`, for instance on another thread while the backend traces other rays)
go to ``intersect_local`` and ``occluded_local``, which only query.

Alpha-tested shadow rays: a backend that can build sub-scenes (``_subscene``) answers ``occluded`` from two of them
(:meth:`Tracer._occluded_split`): the any-hit query runs against the opaque faces, and only the open rays whose
segment crosses the alpha-tested faces' bounding box walk those faces (closest hit, alpha test, re-trace).
``rays_occluded`` counts shadow rays, ``rays_intersect`` every closest-hit query of the walk.

Animated scenes: ``update(t_s)`` moves the scene's rigidly animated objects; backends keep static and moving
geometry apart so that an update rebuilds only what moved.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.errors import UserError
from suite.core.trace.alpha import ALPHA_STEP_ULPS
from suite.core.trace.robust import FLOAT_SCALE


# The largest ray length handed to a backend (Embree's float32 "far" must stay finite).
MAX_RAY_LENGTH = np.float32(1e37)


@dataclass
class Hits:
    t: np.ndarray  # (N,) float32, inf on miss
    prim: np.ndarray  # (N,) int32, -1 on miss
    u: np.ndarray  # (N,) float32
    v: np.ndarray  # (N,) float32

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


def _scratch_array(scratch, name: str, shape, dtype) -> np.ndarray:
    """A reusable array from ``scratch`` (a dict), or a new one without it. Reusing the pages of the previous
    query avoids the page faults of fresh large allocations on every call."""
    if scratch is None:
        return np.empty(shape, dtype)
    size = int(np.prod(shape))
    buf = scratch.get(name)
    if buf is None or buf.size < size or buf.dtype != dtype:
        buf = scratch[name] = np.empty(max(size, 1), dtype)
    return buf[:size].reshape(shape)


_shift_rows_kernel = None


def _shift_rows(o_in: np.ndarray, shift, out: np.ndarray, d=None, tmin=None) -> None:
    """``out[i, c] = float32(float64(o_in[i, c]) - shift[c])`` in one compiled pass over (N, 3) rows (numpy's three
    strided column passes cost a few percent of a backend query); with per-ray ``tmin`` (float32) the origins are
    advanced in the same pass, ``out[i, c] += float32(d[i, c] * tmin[i])`` in float32 as numpy's
    ``o += d * tmin[:, None]`` computes it."""
    global _shift_rows_kernel
    if _shift_rows_kernel is None:
        import numba

        def kernel(o_in, shift, out, d, tmin, advance):
            for i in range(o_in.shape[0]):
                for c in range(3):
                    x = np.float32(np.float64(o_in[i, c]) - shift[c])
                    if advance:
                        x = np.float32(x + np.float32(d[i, c] * tmin[i]))
                    out[i, c] = x

        _shift_rows_kernel = numba.njit(cache=True, nogil=True)(kernel)
    advance = tmin is not None
    _shift_rows_kernel(o_in, np.asarray(shift, np.float64), out, d if advance else np.zeros((1, 3), np.float32),
                       tmin if advance else np.zeros(1, np.float32), advance)


def as_rays(origins, dirs, tmin, tmax, shift=None, soa: bool = False, scratch: dict | None = None):
    """Validates ray arrays, moves origins into the tracing frame (minus ``shift``) and applies ``tmin`` by
    advancing them. Returns (o, d, tmin, length) as float32; ``o`` is (3, N) with ``soa`` (the layout Dr.Jit
    takes without a copy), else (N, 3).

    The subtraction runs in the origins' own precision (float64 G-buffer points stay exact until they are
    small numbers in the tracing frame) and writes float32 directly, without temporaries: it is on the hot
    path of every query.
    """
    o_in = np.asarray(origins)
    o_in = o_in.reshape(-1, 3)
    d = np.ascontiguousarray(dirs, np.float32).reshape(-1, 3)
    if o_in.shape != d.shape:
        raise UserError(f"ray origins {o_in.shape} and directions {d.shape} differ in shape")
    n = len(o_in)
    o = _scratch_array(scratch, "o", (3, n) if soa else (n, 3), np.float32)
    scalar_tmin = np.ndim(tmin) == 0
    has_tmin = not scalar_tmin or tmin > 0
    tmin_a = (np.full(n, np.float32(tmin), np.float32) if scalar_tmin else np.asarray(tmin, np.float32).reshape(n)) \
        if has_tmin else np.float32(0.0)
    if not soa and shift is not None and n >= 4096 and o_in.dtype in (np.float32, np.float64) \
            and o_in.flags.c_contiguous:
        _shift_rows(o_in, shift, o, d, np.ascontiguousarray(tmin_a) if has_tmin else None)
    else:
        # Column by column: numpy's broadcast over a length-3 inner axis is several times slower.
        for c in range(3):
            np.subtract(o_in[:, c], shift[c] if shift is not None else 0.0, out=o[c] if soa else o[:, c],
                        casting="unsafe")
        if has_tmin:
            if soa:
                o += d.T * tmin_a[None, :]
            else:
                o += d * tmin_a[:, None]
    # Lengths are clipped to [0, MAX_RAY_LENGTH] (both backends take a finite float32 far value), in the same
    # pass that makes the float32 copy.
    if np.ndim(tmax) == 0:
        length = _scratch_array(scratch, "length", (n,), np.float32)
        length.fill(np.clip(np.float32(tmax) - np.float32(tmin if scalar_tmin else 0.0), 0.0, MAX_RAY_LENGTH))
        if not scalar_tmin:
            length -= tmin_a
            np.clip(length, 0.0, MAX_RAY_LENGTH, out=length)
    else:
        tmax_a = np.asarray(tmax).reshape(n)
        length = _scratch_array(scratch, "length", (n,), np.float32)
        if has_tmin:
            np.subtract(tmax_a, tmin_a, out=length, casting="unsafe")
            np.clip(length, 0.0, MAX_RAY_LENGTH, out=length)
        else:
            np.clip(tmax_a, 0.0, MAX_RAY_LENGTH, out=length, casting="unsafe")
    return o, d, tmin_a, length


class Tracer:
    """Base class: counters and the shared ray-argument handling."""

    name = "base"
    soa_origins = False  # backends that take (3, N) origins without a copy set this
    normalized_hits = False  # backends whose misses already read t = inf, prim = -1, u = v = 0 set this

    def __init__(self, scene):
        self.scene = scene
        self.counters = {"rays_intersect": 0, "rays_occluded": 0}
        self._time_s = 0.0
        self._scratch: dict = {}  # ray buffers reused across queries (consumed within each call)
        lo, hi = scene.bounds()
        self.shift = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
        from suite.core.trace.alpha import AlphaTest

        self._alpha = AlphaTest.for_scene(scene)  # None unless a material is alpha-tested
        self._groups = None  # (opaque, alpha-tested) sub-scenes of the alpha-aware shadow query, built on first use

    def local_positions(self, positions: np.ndarray) -> np.ndarray:
        """Vertex positions in the tracing frame (float32)."""
        return (positions.astype(np.float64) - self.shift).astype(np.float32)

    # subclasses implement _intersect(o, d, length) -> (t, prim, u, v) and _occluded(o, d, length) -> bool
    def intersect(self, origins, dirs, tmin=0.0, tmax=np.inf) -> Hits:
        o, d, tmin_a, length = as_rays(origins, dirs, tmin, tmax, self.shift, self.soa_origins, self._scratch)
        hits = self.intersect_local(o, d, length)
        if np.ndim(tmin) != 0 or tmin > 0:
            hits.t += tmin_a  # inf stays inf
        return hits

    def intersect_local(self, o, d, length) -> Hits:
        """``intersect`` for rays already in the tracing frame (the arguments of :meth:`occluded_local`, made by
        :func:`as_rays` with this tracer's ``shift`` and ``soa_origins``); ``t`` is measured from ``o``. The
        backend may overwrite ``length``.

        For pipelines that make a query's rays on another thread while the backend traces the previous query
        (:func:`suite.core.pipeline.pipelined`): only the query itself runs on the tracing thread."""
        n = len(d)
        self.counters["rays_intersect"] += n
        if n == 0:
            z = np.zeros(0, np.float32)
            return Hits(z, np.zeros(0, np.int32), z, z)
        if self._alpha is None:
            t, prim, u, v = self._closest(o, d, length)
        else:
            # embreex writes hit distances into the length buffer it is given: keep the lengths for re-tracing.
            t, prim, u, v = self._closest(o, d, length.copy())
            t, prim, u, v = self._skip_transparent(o, d, length, t, prim, u, v)
        return Hits(t, prim, u, v)

    def _closest(self, o, d, length):
        """Backend closest-hit query on tracing-frame rays, misses normalised (t = inf, prim = -1, u = v = 0)."""
        t, prim, u, v = self._intersect(o, d, length)
        t, u, v = (_writable(x) for x in (t, u, v))
        prim = np.asarray(prim, np.int32)
        if not self.normalized_hits:
            _normalize_misses(t, prim, u, v)
        return t, prim, u, v

    def _skip_transparent(self, o, d, length, t, prim, u, v, closest=None):
        """Alpha test (:mod:`suite.core.trace.alpha`): rays whose hit is transparent are traced again from just
        past it, until the hit is opaque, the ray leaves its interval or ``MAX_ALPHA_LAYERS`` are crossed.
        ``t`` is relative to the tracing-frame origins ``o``; every re-traced ray counts in ``rays_intersect``.
        ``closest`` is the closest-hit query of the re-traces (:meth:`_closest`, or a sub-scene's)."""
        from suite.core.trace.alpha import MAX_ALPHA_LAYERS

        closest = self._closest if closest is None else closest
        setup, scatter = _retrace_jit()
        todo = np.flatnonzero(self._alpha.transparent(prim, u, v))
        for _ in range(MAX_ALPHA_LAYERS):
            if len(todo) == 0:
                break
            # Origins just past the transparent hits (alpha.step_past, in its float64 steps); rays left with no
            # length end here as misses (setup writes those and keeps the others first in ``todo``).
            m = len(todo)
            start = np.empty(m, np.float64)
            o_next = np.empty((3, m) if self.soa_origins else (m, 3), np.float32)
            d_next = np.empty((m, 3), np.float32)
            remaining = np.empty(m, np.float32)
            kept = setup(o, self.soa_origins, d, length, t, prim, u, v, todo, start, o_next, d_next, remaining)
            if kept == 0:
                break
            if kept < m:
                todo, start, remaining = todo[:kept], start[:kept], remaining[:kept]
                o_next = np.ascontiguousarray(o_next[:, :kept] if self.soa_origins else o_next[:kept])
                d_next = d_next[:kept]
            self.counters["rays_intersect"] += kept
            t2, p2, u2, v2 = closest(o_next, d_next, remaining)
            scatter(todo, start, t2, p2, u2, v2, t, prim, u, v)
            todo = todo[self._alpha.transparent(p2, u2, v2)]
        return t, prim, u, v

    def _rows(self, o, d, length, idx):
        """The rays ``idx`` of tracing-frame rays, contiguous, in the backend's origin layout."""
        return gather_rays(o, d, length, idx, self.soa_origins)

    def _walk_alpha(self, o, d, length, idx, closest=None):
        """(len(idx),) bool: a closest-hit walk of rays ``idx`` past their transparent hits
        (:meth:`_skip_transparent`) meets an opaque hit within their length."""
        o_sub, d_sub, len_sub = self._rows(o, d, length, idx)
        closest = self._closest if closest is None else closest
        self.counters["rays_intersect"] += len(idx)
        t, prim, u, v = closest(o_sub, d_sub, len_sub.copy())
        _, prim, _, _ = self._skip_transparent(o_sub, d_sub, len_sub, t, prim, u, v, closest)
        return prim >= 0

    def _occluded_alpha(self, o, d, length, occluded):
        """Shadow rays through alpha-tested surfaces: a ray the backend found blocked is blocked only if a closest-hit
        walk past its transparent hits (:meth:`_skip_transparent`) meets an opaque one within its length."""
        idx = np.nonzero(occluded)[0]
        if len(idx) == 0:
            return occluded
        out = np.asarray(occluded, bool).copy()
        out[idx] = self._walk_alpha(o, d, length, idx)
        return out

    def _subscene(self, faces: np.ndarray, positions: np.ndarray):
        """A backend scene over ``faces`` (global indices) at tracing-frame ``positions``, with ``occluded(o, d,
        length)`` and ``closest(o, d, length) -> (t, global prim, u, v)`` (misses normalised); None where the backend
        builds none (then shadow rays take the whole-scene walk)."""
        return None

    def _alpha_groups(self):
        """(opaque, alpha-tested) sub-scenes at the tracer's current time, built on first use and again after
        animated objects moved; None where the backend builds none. The alpha-tested group carries ``box``: the
        bounds of its faces in the tracing frame, padded (:func:`alpha_box`)."""
        if self._groups is None:
            tested = self._alpha.face_tested
            positions = self.scene.positions_at(self._time_s) if self.scene.object_animations else self.scene.positions
            local = self.local_positions(positions)
            alpha_faces = np.nonzero(tested)[0].astype(np.int32)
            opaque = self._subscene(np.nonzero(~tested)[0].astype(np.int32), local)
            alpha = self._subscene(alpha_faces, local) if opaque is not None else None
            if alpha is not None:
                alpha.box = alpha_box(local[self.scene.faces[alpha_faces]].reshape(-1, 3), local)
            self._groups = (opaque, alpha) if alpha is not None else False
        return self._groups or None

    def _occluded_split(self, o, d, length):
        """Shadow rays through alpha-tested surfaces: an any-hit query against the opaque faces (blocked for good); the
        open rays whose segment crosses the alpha-tested faces' padded box (a conservative test,
        :func:`box_candidates`) walk those faces only (closest hit, alpha test, re-trace past transparent texels); a
        ray that misses the box cannot meet an alpha-tested face. One full query per ray, as the backend's raw query
        makes, plus the walk. The same answer as the whole-scene walk of :meth:`_occluded_alpha` except where an
        opaque face lies within the re-trace step (``ALPHA_STEP_ULPS``) behind a transparent texel or ties with it:
        there the opaque face blocks the ray."""
        groups = self._alpha_groups()
        if groups is None:
            return self._occluded_alpha(o, d, length, np.array(self._occluded(o, d, length.copy()), bool))
        opaque, alpha = groups
        occ = np.array(opaque.occluded(o, d, length.copy()), bool)  # embreex overwrites the lengths it is given
        walk = box_candidates(o, d, length, alpha.box, self.soa_origins, blocked=occ)
        if len(walk):
            occ[walk] = self._walk_alpha(o, d, length, walk, alpha.closest)
        return occ

    def occluded(self, origins, dirs, tmin=0.0, tmax=np.inf) -> np.ndarray:
        o, d, _, length = as_rays(origins, dirs, tmin, tmax, self.shift, self.soa_origins, self._scratch)
        self.counters["rays_occluded"] += len(d)
        if len(d) == 0:
            return np.zeros(0, bool)
        if self._alpha is None:
            return self._occluded(o, d, length)
        return self._occluded_split(o, d, length)

    def occluded_local(self, o, d, length) -> np.ndarray:
        """``occluded`` for rays already in the tracing frame: float32 origins minus ``shift`` (shape (3, N) if
        ``soa_origins`` else (N, 3)), unit float32 directions (N, 3), lengths in [0, MAX_RAY_LENGTH].

        For ray generators that write rays in the backend's frame and layout directly
        (:mod:`suite.core.trace.raygen`); everything else should call :meth:`occluded`.
        """
        n = len(d)
        self.counters["rays_occluded"] += n
        if n == 0:
            return np.zeros(0, bool)
        if self._alpha is None:
            return self._occluded(o, d, length)
        return self._occluded_split(o, d, length)

    def update(self, t_s: float) -> None:
        """Moves animated objects to their pose at ``t_s`` (no-op for static scenes)."""
        if not self.scene.object_animations or t_s == self._time_s:
            self._time_s = t_s
            return
        self._update(t_s)
        self._time_s = t_s
        self._groups = None  # the alpha groups hold the old positions

    def reset_counters(self) -> None:
        for k in self.counters:
            self.counters[k] = 0

    def describe(self) -> dict:
        return {"backend": self.name}

    def _update(self, t_s: float) -> None:
        raise NotImplementedError


_normalize_misses_kernel = None


def _normalize_misses(t, prim, u, v) -> None:
    """``t = inf, u = v = 0`` where ``prim < 0``, in place, in one compiled pass (three masked numpy assignments cost
    about 8 % of an Embree closest-hit query)."""
    global _normalize_misses_kernel
    if _normalize_misses_kernel is None:
        import numba

        def kernel(t, prim, u, v):
            # Selects rather than a branch: the loop vectorises (a third faster on mostly-missing shadow rays).
            inf, zero = t.dtype.type(np.inf), u.dtype.type(0.0)
            for i in range(prim.shape[0]):
                miss = prim[i] < 0
                t[i] = inf if miss else t[i]
                u[i] = zero if miss else u[i]
                v[i] = zero if miss else v[i]

        _normalize_misses_kernel = numba.njit(cache=True, nogil=True)(kernel)
    _normalize_misses_kernel(t, prim, u, v)


# Padding of the alpha-tested faces' box, relative to the scene's extent, and of the ray lengths in the box test:
# far above float32 rounding of hit points and distances, so a ray the backend finds hitting such a face always
# crosses the box.
ALPHA_BOX_PAD = 1e-4


def alpha_box(points: np.ndarray, all_points: np.ndarray):
    """(2, 3) float64 [lo, hi] of ``points`` padded by ``ALPHA_BOX_PAD`` of the extent of ``all_points`` (an empty
    box, lo > hi, without points)."""
    if len(points) == 0:
        return np.array([[np.inf] * 3, [-np.inf] * 3])
    extent = float(np.max(all_points.max(axis=0).astype(np.float64) - all_points.min(axis=0)))
    pad = ALPHA_BOX_PAD * max(extent, 1e-6)
    return np.stack([points.min(axis=0).astype(np.float64) - pad, points.max(axis=0).astype(np.float64) + pad])


_kernels = None


def _box_hits(o, d, length, lo, hi, soa, blocked, out) -> int:
    """Writes to ``out`` the indices of the rays that are not ``blocked`` (where ``blocked`` is not empty) and whose
    segment o + t d, 0 <= t <= length (padded), crosses the box [lo, hi] (float32 ``lo``, ``hi``); returns their
    count. A slab test in float32 with reciprocal directions: a filter only, whose rounding (a few float32 ULPs of
    the distances) lies far inside the box's padding. A zero direction component keeps the segment in its slab or
    out of it."""
    skip = blocked.shape[0] > 0
    k = 0
    for i in range(d.shape[0]):
        if skip and blocked[i]:
            continue
        t0 = np.float32(0.0)
        t1 = length[i] * np.float32(1.0 + ALPHA_BOX_PAD) + np.float32(1e-6)
        ok = True
        for c in range(3):
            oc = o[c, i] if soa else o[i, c]
            dc = d[i, c]
            if dc == 0.0:
                ok = ok and lo[c] <= oc <= hi[c]
                continue
            inv = np.float32(1.0) / dc
            a = (lo[c] - oc) * inv
            b = (hi[c] - oc) * inv
            t0 = max(t0, min(a, b))
            t1 = min(t1, max(a, b))
        if ok and t0 <= t1:
            out[k] = i
            k += 1
    return k


def _retrace_setup(o, soa, d, length, t, prim, u, v, todo, start, o_next, d_next, remaining) -> int:
    """The re-trace rays of :meth:`Tracer._skip_transparent` for the hits ``todo`` (transparent), in one pass:
    ``start`` = :func:`suite.core.trace.alpha.step_past` of each hit (its float64 steps), origins ``o + d start``
    rounded to float32 (in ``o``'s layout), ``remaining = length - start``. Rays with no length left become misses
    in (t, prim, u, v); the others are compacted to the front of ``todo`` and the outputs, and their count returned."""
    k = 0
    for j in range(todo.shape[0]):
        i = todo[j]
        ti = np.float64(t[i])
        p = 0.0
        for c in range(3):
            oc = o[c, i] if soa else o[i, c]
            p = max(p, abs(np.float64(oc) + np.float64(d[i, c]) * ti))
        scale = np.float32(max(p, abs(ti)))
        s = ti + max(ALPHA_STEP_ULPS * np.float64(np.spacing(scale)), FLOAT_SCALE)
        rem = np.float64(length[i]) - s
        if rem <= 0:
            t[i], prim[i], u[i], v[i] = np.inf, -1, 0.0, 0.0
            continue
        todo[k] = i
        start[k] = s
        remaining[k] = np.float32(rem)
        for c in range(3):
            oc = o[c, i] if soa else o[i, c]
            x = np.float32(np.float64(oc) + np.float64(d[i, c]) * s)
            if soa:
                o_next[c, k] = x
            else:
                o_next[k, c] = x
            d_next[k, c] = d[i, c]
        k += 1
    return k


def _retrace_scatter(todo, start, t2, p2, u2, v2, t, prim, u, v):
    """The re-traced hits back into (t, prim, u, v): distances from the original origins (``start + t2``, float32),
    misses at infinity."""
    for j in range(todo.shape[0]):
        i = todo[j]
        t[i] = np.float32(start[j] + np.float64(t2[j])) if p2[j] >= 0 else np.float32(np.inf)
        prim[i] = p2[j]
        u[i] = u2[j]
        v[i] = v2[j]


def _gather_rays(o, d, length, idx, soa, o_out, d_out, len_out):
    """Rows ``idx`` of tracing-frame rays, contiguous, in the origins' own layout."""
    for k in range(idx.shape[0]):
        i = idx[k]
        for c in range(3):
            if soa:
                o_out[c, k] = o[c, i]
            else:
                o_out[k, c] = o[i, c]
            d_out[k, c] = d[i, c]
        len_out[k] = length[i]


def _compiled():
    """The compiled ray kernels of this module: (box test, gather, re-trace setup, re-trace scatter)."""
    global _kernels
    if _kernels is None:
        import numba

        jit = numba.njit(cache=True, nogil=True)
        _kernels = (jit(_box_hits), jit(_gather_rays), jit(_retrace_setup), jit(_retrace_scatter))
    return _kernels


def _box_jit():
    return _compiled()[:2]


def _retrace_jit():
    return _compiled()[2:]


_NO_MASK = np.zeros(0, bool)


def box_candidates(o, d, length, box, soa: bool, blocked=None) -> np.ndarray:
    """Indices of the tracing-frame rays (origins (3, N) if ``soa`` else (N, 3), unit directions (N, 3), lengths) whose
    segments cross ``box`` ((2, 3) float64, padded): a conservative test, a segment that meets anything inside the box
    is among them. ``blocked``: rays to leave out."""
    idx = np.empty(len(d), np.int64)
    k = _box_jit()[0](o, d, length, np.ascontiguousarray(box[0], np.float32), np.ascontiguousarray(box[1], np.float32),
                      soa, _NO_MASK if blocked is None else np.ascontiguousarray(blocked, bool), idx)
    return idx[:k]


def gather_rays(o, d, length, idx, soa: bool):
    """(o, d, length) of rays ``idx``, contiguous, origins in the same layout (one compiled pass; numpy's fancy
    indexing of rows is several times slower)."""
    m = len(idx)
    o_out = np.empty((3, m) if soa else (m, 3), np.float32)
    d_out = np.empty((m, 3), np.float32)
    len_out = np.empty(m, np.float32)
    _box_jit()[1](o, d, length, np.asarray(idx, np.int64), soa, o_out, d_out, len_out)
    return o_out, d_out, len_out


def _writable(x) -> np.ndarray:
    """float32 array that may be modified in place (copies only when the backend's buffer is read-only)."""
    a = np.asarray(x, np.float32)
    return a if a.flags.writeable and a.flags.owndata else a.copy()


def split_static_dynamic(scene):
    """Face indices of static geometry and of rigidly animated objects."""
    moving = np.array(sorted({a.object_id for a in scene.object_animations}), np.int32)
    is_dynamic = np.isin(scene.face_object, moving)
    return np.nonzero(~is_dynamic)[0].astype(np.int32), np.nonzero(is_dynamic)[0].astype(np.int32)
