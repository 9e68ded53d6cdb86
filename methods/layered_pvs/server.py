"""Server side of seed 002 (Fig. 4.2, chapters 4-5): predicted views and PVS (Algorithm 1, §4.1.1), ray-traced
depth peeling restricted to the PVS (§4.1.2), path tracing of every layer fragment (§4.4: next-event estimation,
Russian roulette) and SVGF extended to layers (§4.4.1, Algorithm 4).

All functions are pure numpy / numba on arrays plus calls to a suite tracer, so that rays are counted by the
harness and both backends (Embree, Mitsuba) serve them.
"""
from __future__ import annotations

import math
import os
import threading
from contextlib import nullcontext
from dataclasses import dataclass
from functools import partial
from types import SimpleNamespace

import numpy as np

from suite.core import shading
from suite.core.gbuffer import camera_rays, surface_attributes
from suite.core.pipeline import SerialTracer
from suite.core.rng import dim_hashes, hashed_uniforms, pcg_np
from suite.core.scene.model import CameraPose
from suite.core.trace.base import MAX_RAY_LENGTH
from suite.core.trace.robust import offset_ray_origin

from methods.layered_pvs import kernels

SHADOW_TMAX_SCALE = 1.0 - 1e-4
PEEL_REL_EPS = 1e-5         # depth peeling: the next layer starts this far (relative) past the previous hit


# ------------------------------------------------------------------------------------------ views

@dataclass(frozen=True)
class LayerView:
    """The camera of the layers: the update's pose with the enlarged field of view (§4.1.2)."""

    pose: CameraPose
    fov_deg: float          # horizontal
    width: int
    height: int


def layer_size(width: int, height: int, fov_deg: float, enlarge: float, tile: int) -> tuple[int, int, float]:
    """Layer size for a client of ``width`` x ``height`` whose horizontal and vertical fields of view are enlarged
    by ``enlarge`` at the client's pixel density (§6: 1920x1080 at 1.1x gives 2254x1214), rounded up to whole
    tiles; returns (W_l, H_l, horizontal fov of the layers in degrees)."""
    tan_x = math.tan(math.radians(fov_deg) / 2)
    tan_y = tan_x * height / width
    wl = width * math.tan(enlarge * math.atan(tan_x)) / tan_x
    hl = height * math.tan(enlarge * math.atan(tan_y)) / tan_y
    wl = int(math.ceil(round(wl, 6) / tile)) * tile
    hl = int(math.ceil(round(hl, 6) / tile)) * tile
    # Same angular density as the client: the layer's tangent extents grow with its pixel count.
    fov_l = math.degrees(2 * math.atan(tan_x * wl / width))
    return wl, hl, fov_l


def predict_views(history: list, period_s: float, corner_offset: float) -> list[CameraPose]:
    """Algorithm 1's seven views from poses the client sent (``history``: (t_s, pose), oldest first): the current
    view, four corners on the plane perpendicular to it at ``corner_offset`` (adapted to the update period by the
    caller), and two extrapolated in time (one and two update periods ahead, from the last two poses)."""
    t1, cur = history[-1]
    f, r, u = cur.basis()
    p = np.asarray(cur.position, np.float64)
    tgt = np.asarray(cur.target, np.float64)
    views = [cur]
    for sx, sy in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
        off = corner_offset * (sx * r + sy * u)
        views.append(CameraPose(p + off, tgt + off, cur.up))
    if len(history) >= 2 and history[-1][0] > history[-2][0]:
        t0, prev = history[-2]
        dt = t1 - t0
        v = (p - np.asarray(prev.position, np.float64)) / dt
        f_prev = prev.basis()[0]
        dfwd = (f - f_prev) / dt
        for k in (1, 2):
            pk = p + v * (k * period_s)
            fk = f + dfwd * (k * period_s)
            n = np.linalg.norm(fk)
            fk = fk / n if n > 1e-12 else f
            views.append(CameraPose(pk, pk + fk, cur.up))
    else:
        views += [cur, cur]     # no motion known yet: the current view again
    return views


def view_rays(view: LayerView):
    return camera_rays(view.pose, view.fov_deg, view.width, view.height, dtype=np.float64)


def compute_pvs(tracer, views, fov_deg: float, width: int, height: int) -> np.ndarray:
    """Algorithm 1: triangle ids seen from the views (an id buffer per view, by ray casting against the whole
    scene), marked and compacted (the prefix sum of the thesis = ``np.nonzero`` of the marks). Sorted ids.

    A view equal to an earlier one (the extrapolated views of a camera with no known motion) adds nothing and is
    not traced again. The views run through the host pipeline (:func:`suite.core.pipeline.pipelined`): a worker
    makes the next view's camera rays (compiled, the GIL released) and marks the previous view's ids while the
    backend traces the current one's."""
    from suite.core.pipeline import local_rays, pipelined, trace_local

    marks = np.zeros(tracer.scene.num_faces, bool)
    distinct = {}
    for pose in views:
        key = tuple(np.concatenate([np.asarray(v, np.float64).reshape(3) for v in (pose.position, pose.target,
                                                                                    pose.up)]))
        distinct.setdefault(key, pose)
    if getattr(tracer, "device", None) is not None:
        from methods.layered_pvs import device as layered_device

        return layered_device.compute_pvs(tracer.device, list(distinct.values()), fov_deg, width, height)
    rays, hits = {}, {}

    def step(i, pose):
        def make():
            # float32 rays straight from the compiled camera pass (its float64 directions rounded once, as a
            # float64 pass and a cast would give them, without the two extra copies)
            o, d = camera_rays(pose, fov_deg, width, height, dtype=np.float32)
            rays[i] = (local_rays(tracer, o, d), o, d)

        def trace():
            hits[i] = trace_local(tracer, *rays.pop(i)).prim

        def finish():
            prim = hits.pop(i)
            marks[prim[prim >= 0]] = True

        return make, trace, finish

    pipelined([step(i, pose) for i, pose in enumerate(distinct.values())])
    return np.nonzero(marks)[0].astype(np.int64)


# ------------------------------------------------------------------------------------------ depth peeling

@dataclass
class Layers:
    t: np.ndarray        # (L, H, W) float32 distance along the ray (inf = empty)
    prim: np.ndarray     # (L, H, W) int64 triangle (scene id on the server, PVS index on the client), -1 = empty
    u: np.ndarray
    v: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.prim >= 0

    @property
    def counts(self) -> np.ndarray:
        return self.valid.sum(axis=0)


def peel(tracer, origins: np.ndarray | None, dirs: np.ndarray | None, layers: int, keep=None, max_skips: int = 256,
         shape=None, keep_mask: np.ndarray | None = None, view: LayerView | None = None) -> Layers:
    """Ray-traced depth peeling (§4.1.2): layer k is the nearest hit past layer k-1's hit (``tmin`` = that distance
    plus a relative epsilon). ``keep_mask`` (bool per triangle; or ``keep``, prim -> bool) restricts primary hits to
    the PVS: a hit on another triangle is stepped over and the ray traced again from just past it (secondary and
    shadow rays are not affected). ``tracer`` answers ``intersect_local`` on rays in its frame (its ``shift`` and
    ``soa_origins``); origins and directions float32 (N, 3).

    Between queries, one compiled pass (:mod:`methods.layered_pvs.kernels`) takes in the hits and writes the next
    query's rays, already in the tracer's frame and with their lengths (the arrays ``Tracer.intersect`` would make
    of origins, directions and ``tmin``), into buffers allocated once; a ``keep`` callable takes
    :func:`peel_reference` instead. ``view`` (``origins`` and ``dirs`` None): the layer view's pixel-centre rays
    (:func:`view_rays`), made on the device on a Dr.Jit tracer."""
    if view is not None and getattr(tracer, "device", None) is not None and keep is None:
        from methods.layered_pvs import device as layered_device

        out = layered_device.peel(tracer.device, None, None, layers, keep_mask, max_skips, view=view)
        shp = (layers,) + tuple(shape) if shape is not None else (layers, view.width * view.height)
        return Layers(*(a.reshape(shp) for a in out))
    if view is not None:
        o64, d64 = view_rays(view)
        origins, dirs = o64.astype(np.float32), d64.astype(np.float32)
    if keep is not None and keep_mask is None:
        return peel_reference(tracer.intersect, origins, dirs, layers, keep, max_skips, shape)
    shp = (layers,) + tuple(shape) if shape is not None else (layers, len(dirs))
    if getattr(tracer, "device", None) is not None:
        from methods.layered_pvs import device as layered_device

        out = layered_device.peel(tracer.device, origins, dirs, layers, keep_mask, max_skips)
        return Layers(*(a.reshape(shp) for a in out))
    kern = kernels.jit()
    n = len(dirs)
    t_out = np.full((layers, n), np.inf, np.float32)
    p_out = np.full((layers, n), -1, np.int64)
    u_out = np.zeros((layers, n), np.float32)
    v_out = np.zeros((layers, n), np.float32)
    use_keep = keep_mask is not None
    mask = np.ascontiguousarray(keep_mask, np.bool_) if use_keep else np.zeros(1, np.bool_)
    origins, dirs = np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32)
    scale32 = np.float32(1 + PEEL_REL_EPS)
    shift = np.zeros(3) if getattr(tracer, "shift", None) is None else np.asarray(tracer.shift, np.float64)
    soa = bool(getattr(tracer, "soa_origins", False))
    # The queries of this layer and of the next: pixel, start distance, tracing-frame origin, direction and length
    # of each ray, allocated once.
    query, nxt = ((np.empty(n, np.int64), np.empty(n, np.float32), np.empty((n, 3), np.float32),
                   np.empty((n, 3), np.float32), np.empty(n, np.float32)) for _ in range(2))
    m = kern["_peel_first"](origins, dirs, shift, MAX_RAY_LENGTH, *query)
    # On a host tracer a large query is traced in runs (:data:`PEEL_RUNS`) and each run's hits are taken in on a
    # worker while the next run is traced. The runs are taken in in order, each appending where the previous one
    # stopped, so the queries and layers are those of whole queries.
    host = getattr(tracer, "device", None) is None
    with _Handoff() if host else nullcontext() as worker:
        for k in range(layers):
            idx, start, o, d, length = query
            m_next = 0
            for _ in range(max_skips):
                if m == 0:
                    break
                skips = 0
                split = worker is not None and m >= PEEL_SPLIT_MIN
                bounds = np.round(np.array(PEEL_RUNS if split else (0.0, 1.0)) * m).astype(np.int64)
                for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
                    h = tracer.intersect_local(np.ascontiguousarray(o[a:b].T) if soa else o[a:b], d[a:b],
                                               length[a:b])
                    if split and a > 0:
                        skips, m_next = worker.result()
                    # Run [a, b) is compacted to slots from ``skips`` on: below every slot it has still to read.
                    args = (h.prim, h.t, h.u, h.v, idx[a:b], start[a:b], mask, use_keep, k, scale32, t_out, p_out,
                            u_out, v_out, origins, dirs, shift, MAX_RAY_LENGTH, *(q[skips:] for q in query),
                            k + 1 < layers, m_next, *nxt)
                    if split and b < m:
                        worker.start(_taken_in, kern["_peel_hits"], skips, args)
                    else:
                        taken, m_next = kern["_peel_hits"](*args)
                        skips += taken
                m = skips
            query, nxt, m = nxt, query, m_next
            if m == 0:
                break
    return Layers(t_out.reshape(shp), p_out.reshape(shp), u_out.reshape(shp), v_out.reshape(shp))


# Runs of a large peeling query (fractions of its rays): the hits of each run but the last are taken in on the
# worker while the next run is traced; the last run is short, as its hits are taken in on the tracing thread. Below
# PEEL_SPLIT_MIN rays a query stays whole (the hand-over costs more than the pass it would hide).
PEEL_RUNS = (0.0, 0.45, 0.9, 1.0)
PEEL_SPLIT_MIN = 1 << 15


def _taken_in(peel_hits, skips, args):
    taken, m_next = peel_hits(*args)
    return skips + taken, m_next


class _Handoff:
    """One worker thread that runs one compiled pass at a time beside the caller's queries. :meth:`start` returns
    once the worker has called the pass: the worker holds the GIL from taking the job until the pass releases it,
    so the caller's next query (which holds the GIL throughout on embreex) cannot start before the pass is running
    and shut it out."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(1, thread_name_prefix="splitbench-peel")
        self._called = threading.Event()
        self._pending = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._pending is not None:
            self._pending.exception()  # wait for a pass still running (its error, if any, was the caller's to see)
        self._pool.shutdown()

    def start(self, fn, *args) -> None:
        def job():
            self._called.set()
            return fn(*args)

        self._called.clear()
        self._pending = self._pool.submit(job)
        self._called.wait()

    def result(self):
        pending, self._pending = self._pending, None
        return pending.result()


def peel_reference(intersect, origins: np.ndarray, dirs: np.ndarray, layers: int, keep=None,
                   max_skips: int = 256, shape=None) -> Layers:
    """:func:`peel` as whole-array numpy expressions (gathers, masks and scatters per query), with ``keep`` any
    callable prim -> bool: the reference its compiled passes are tested against."""
    n = len(dirs)
    t_out = np.full((layers, n), np.inf, np.float32)
    p_out = np.full((layers, n), -1, np.int64)
    u_out = np.zeros((layers, n), np.float32)
    v_out = np.zeros((layers, n), np.float32)
    tmin = np.zeros(n, np.float32)
    alive = np.arange(n)
    for k in range(layers):
        idx = alive
        start = tmin[idx]
        for _ in range(max_skips):
            if len(idx) == 0:
                break
            h = intersect(origins[idx], dirs[idx], start)
            hit = h.prim >= 0
            ok = hit if keep is None else hit & keep(np.maximum(h.prim, 0))
            done = ok | ~hit
            sel = idx[ok]
            t_out[k, sel], p_out[k, sel], u_out[k, sel], v_out[k, sel] = h.t[ok], h.prim[ok], h.u[ok], h.v[ok]
            skip = ~done
            idx, start = idx[skip], past(h.t[skip])
        alive = np.nonzero(p_out[k] >= 0)[0]
        tmin[alive] = past(t_out[k, alive])
        if len(alive) == 0:
            break
    shp = (layers,) + tuple(shape) if shape is not None else (layers, n)
    return Layers(t_out.reshape(shp), p_out.reshape(shp), u_out.reshape(shp), v_out.reshape(shp))


def past(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, np.float32)
    return np.nextafter(t * np.float32(1 + PEEL_REL_EPS), np.float32(np.inf)).astype(np.float32)


# ------------------------------------------------------------------------------------------ path tracing

@dataclass
class Fragments:
    """Surface data of every layer fragment, flattened (N = number of fragments)."""

    index: tuple            # (k, y, x) arrays into the layer grid
    position: np.ndarray    # (N, 3) float64
    geo_normal: np.ndarray  # (N, 3) facing the layer camera
    normal: np.ndarray      # (N, 3) shading normal facing the layer camera
    albedo: np.ndarray      # (N, 3)
    emission: np.ndarray    # (N, 3) (front-facing emitters only)
    view_dir: np.ndarray    # (N, 3) float64
    # made on a Dr.Jit device (methods.layered_pvs.device.fragments): the position (Point3d) and the normals
    # (Vector3d) still there, for the device passes that read them (None otherwise)
    device: SimpleNamespace | None = None


def _facing(ng, ns, d):
    flip = np.sign(np.einsum("ij,ij->i", ng, d))[:, None]
    flip[flip == 0] = 1.0
    ng_f = -flip * ng
    ns_f = np.where(np.einsum("ij,ij->i", ns, ng_f)[:, None] < 0, -ns, ns)
    return ng_f, ns_f, flip[:, 0] < 0


def fragments(scene, layers: Layers, origins64: np.ndarray | None, dirs64: np.ndarray | None, t_s: float,
              device=None, view: LayerView | None = None) -> Fragments:
    """Every layer fragment's surface (:func:`suite.core.gbuffer.surface_attributes`), its normals facing the layer
    camera and its emission on front faces only. The gathers and the facing are compiled passes
    (:mod:`methods.layered_pvs.kernels`) with the bits of :func:`fragments_reference`; the fragments are split into
    contiguous runs, one per core (:data:`FRAGMENT_RUN_MIN` at least), each on a thread of its own (the passes
    write their rows of shared outputs and release the GIL). ``device``: a Dr.Jit device (a Mitsuba tracer's) to
    make them on instead (:func:`methods.layered_pvs.device.fragments`, the same bits on ``llvm_ad_rgb``). ``view``
    (``origins64`` and ``dirs64`` None): the layer view's rays (:func:`view_rays`; made on the device there)."""
    if device is not None:
        from methods.layered_pvs import device as layered_device

        return layered_device.fragments(device, layers, origins64, dirs64, t_s, view=view)
    if view is not None and origins64 is None:
        origins64, dirs64 = view_rays(view)
    kern = kernels.jit()
    k, y, x = np.nonzero(layers.valid)
    n = len(k)
    prim, u, v = np.empty(n, np.int64), np.empty(n, np.float32), np.empty(n, np.float32)
    o, d = np.empty((n, 3)), np.empty((n, 3))
    p, ng, ns = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    alb, em = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    ng_f, ns_f, em_f, front = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3), np.float32), np.empty(n, np.bool_)
    layer_prim = np.ascontiguousarray(layers.prim, np.int64)
    layer_u, layer_v = np.ascontiguousarray(layers.u, np.float32), np.ascontiguousarray(layers.v, np.float32)
    origins64, dirs64 = np.ascontiguousarray(origins64, np.float64), np.ascontiguousarray(dirs64, np.float64)
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)

    def run(a: int, b: int) -> None:
        r = slice(a, b)
        kern["_gather_fragments"](k[r], y[r], x[r], layer_prim, layer_u, layer_v, origins64, dirs64, prim[r], u[r],
                                  v[r], o[r], d[r])
        surface_attributes(scene, positions, normals, prim[r], u[r], v[r], o[r], d[r],
                           out=(p[r], ng[r], ns[r], alb[r], em[r]))
        kern["_face_fragments"](ng[r], ns[r], d[r], em[r], ng_f[r], ns_f[r], em_f[r], front[r])

    runs = max(1, min(os.cpu_count() or 1, n // FRAGMENT_RUN_MIN))
    bounds = np.linspace(0, n, runs + 1).astype(np.int64)
    if runs == 1:
        run(0, n)
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(runs - 1) as pool:
            pending = [pool.submit(run, int(a), int(b)) for a, b in zip(bounds[1:-1], bounds[2:])]
            run(0, int(bounds[1]))
            for f in pending:
                f.result()
    return Fragments((k, y, x), p, ng_f, ns_f, alb, em_f, d)


# The fewest fragments worth a thread of their own in :func:`fragments` (below, one run: a thread's start-up and the
# shared tables' set-up cost more than the rows take).
FRAGMENT_RUN_MIN = 1 << 15


def fragments_reference(scene, layers: Layers, origins64: np.ndarray, dirs64: np.ndarray, t_s: float) -> Fragments:
    """:func:`fragments` as numpy gathers and :func:`_facing` (the reference its compiled passes are tested
    against)."""
    w = layers.prim.shape[2]
    k, y, x = np.nonzero(layers.valid)
    pix = y * w + x
    prim = layers.prim[k, y, x]
    o, d = origins64[pix], dirs64[pix]
    p, ng, ns, alb, em = surface_attributes(scene, scene.positions_at(t_s), scene.normals_at(t_s), prim,
                                            layers.u[k, y, x], layers.v[k, y, x], o, d)
    ng_f, ns_f, front = _facing(ng, ns, d)
    em = np.where(front[:, None], em, 0.0)
    return Fragments((k, y, x), p, ng_f, ns_f, alb, em, d)


class LightSampler:
    """Point lights and emissive triangles for next-event estimation at the path vertices after the primary
    fragment (§4.4: one randomly selected light per vertex). With at most ``PER_POINT_LIGHTS`` lights a light
    is chosen in proportion to its unoccluded irradiance bound at the shading point (power / squared distance, a
    triangle at its centroid); with more, in proportion to power. Both are unbiased; the first keeps far, strong
    lights (the 10 km sun and sky lights of the Quake levels) from taking nearly every sample from the nearby
    ones."""

    PER_POINT_LIGHTS = 2048
    CHUNK_ELEMENTS = 1 << 21     # points x lights per block of the per-point choice

    def __init__(self, scene, t_s: float):
        lights = scene.lights_at(t_s)
        self.point_pos = np.array([lt.position for lt in lights], np.float64).reshape(-1, 3)
        self.point_int = np.array([lt.intensity for lt in lights], np.float64).reshape(-1, 3)
        if any(m.is_emissive for m in scene.materials):
            tl = scene.area_light_triangles(t_s)
            self.tri = tl.vertices.reshape(-1, 3, 3)
            self.tri_n = tl.normal.reshape(-1, 3)
            self.tri_l = tl.radiance.reshape(-1, 3)
            self.tri_area = tl.area.reshape(-1)
        else:
            # no emitter: the empty light list without gathering every triangle of the scene (a few ms per update)
            self.tri, self.tri_n, self.tri_l, self.tri_area = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)), \
                np.zeros(0)
        power = np.concatenate([4 * np.pi * self.point_int.mean(axis=1),
                                np.pi * self.tri_area * self.tri_l.mean(axis=1)])
        total = power.sum()
        self.n_point = len(self.point_pos)
        self.pmf = power / total if total > 0 else np.zeros_like(power)
        self.cdf = np.cumsum(self.pmf)
        self.power = power
        self.centres = np.concatenate([self.point_pos, self.tri.mean(axis=1)]) if len(self.tri) else self.point_pos
        self.min_d2 = (1e-3 * float(np.linalg.norm(np.ptp(self.centres, axis=0)) + 1e-6)) ** 2 \
            if len(self.centres) else 1.0

    def choose(self, p, u_sel):
        """Light index per point and its selection probability."""
        n = len(p)
        if len(self.power) > self.PER_POINT_LIGHTS or n == 0:
            j = np.minimum(np.searchsorted(self.cdf, u_sel * self.cdf[-1], side="right"), len(self.cdf) - 1)
            return j, self.pmf[j]
        j = np.zeros(n, np.int64)
        pmf = np.zeros(n)
        rows = max(64, self.CHUNK_ELEMENTS // max(len(self.power), 1))
        for a in range(0, n, rows):
            b = min(a + rows, n)
            d2 = ((p[a:b, None, :] - self.centres[None, :, :]) ** 2).sum(-1)
            w = self.power[None, :] / np.maximum(d2, self.min_d2)
            cdf = np.cumsum(w, axis=1)
            tot = cdf[:, -1]
            jj = np.minimum((cdf < (u_sel[a:b] * tot)[:, None]).sum(axis=1), len(self.power) - 1)
            j[a:b] = jj
            pmf[a:b] = w[np.arange(b - a), jj] / np.maximum(tot, 1e-300)
        return j, pmf

    def __len__(self):
        return int((self.pmf > 0).sum())

    def kernel_args(self) -> tuple:
        """The light arrays in the order :func:`methods.layered_pvs.kernels._shade_vertex` takes them (the choice
        per point as :meth:`choose` makes it, the sample as :meth:`sample` draws it)."""
        c = np.ascontiguousarray
        return (len(self.power) <= self.PER_POINT_LIGHTS, c(self.power), c(self.centres), float(self.min_d2),
                c(self.cdf), c(self.pmf), int(self.n_point), c(self.point_pos), c(self.point_int), c(self.tri),
                c(self.tri_n), c(self.tri_l), c(self.tri_area))

    def sample(self, p, u_sel, u2):
        """Per point: direction, distance, radiance-weighted contribution factor (L cos_y / (d^2 pdf)), validity."""
        n = len(p)
        j, pmf = self.choose(p, u_sel)
        is_pt = j < self.n_point
        target = np.zeros((n, 3))
        weight = np.zeros((n, 3))
        ok = np.zeros(n, bool)
        if is_pt.any():
            jp = j[is_pt]
            target[is_pt] = self.point_pos[jp]
            d2 = np.maximum(((target[is_pt] - p[is_pt]) ** 2).sum(1), 1e-12)
            weight[is_pt] = self.point_int[jp] / d2[:, None] / pmf[is_pt][:, None]
            ok[is_pt] = True
        ar = ~is_pt
        if ar.any():
            jt = j[ar] - self.n_point
            su = np.sqrt(u2[ar, 0])
            b1, b2 = 1 - su, u2[ar, 1] * su
            tri = self.tri[jt]
            y = tri[:, 0] + b1[:, None] * (tri[:, 1] - tri[:, 0]) + b2[:, None] * (tri[:, 2] - tri[:, 0])
            target[ar] = y
            to = y - p[ar]
            d2 = np.maximum((to ** 2).sum(1), 1e-12)
            wi = to / np.sqrt(d2)[:, None]
            cos_y = -(wi * self.tri_n[jt]).sum(1)
            good = cos_y > 0
            weight[ar] = np.where(good[:, None], self.tri_l[jt] * (cos_y * self.tri_area[jt] / d2
                                                                   / pmf[ar])[:, None], 0.0)
            ok[ar] = good
        to = target - p
        dist = np.linalg.norm(to, axis=1)
        wi = to / np.maximum(dist, 1e-30)[:, None]
        return wi, dist, weight, ok


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _cosine_hemisphere(n, u):
    r = np.sqrt(u[:, 0])
    phi = 2 * np.pi * u[:, 1]
    lx, ly, lz = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u[:, 0]))
    a = np.where(np.abs(n[:, 0:1]) > 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    t = np.cross(n, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    return lx[:, None] * t + ly[:, None] * b + lz[:, None] * n


def direct_illumination(scene, tracer, frag: Fragments, t_s: float, area_samples: int, seed: int) -> np.ndarray:
    """Demodulated direct illumination (N, 3) at the fragments, the estimate of the suite's direct-lighting kernels
    (:func:`suite.core.shading.compose_direct`, host path): every point light with its own shadow ray, area
    lights with ``area_samples`` stratified samples. The fragments are shaded as an (N, 1) G-buffer of albedo 1
    without emission.

    On a host tracer the point lights take the suite's compiled shadow rays (:class:`suite.core.trace.raygen
    .ShadowRays`, the same rays) and one compiled shading pass (:mod:`methods.layered_pvs.kernels`, the bits of
    ``shade_point_lights``) instead of ``compose_direct``'s thread pool and (N, 1, 3) numpy passes, and the scene
    extent behind the light clamp distance is taken once per scene; a tracer with a device path takes
    ``compose_direct`` itself (:func:`direct_illumination_reference`)."""
    if getattr(tracer, "device", None) is not None:
        return direct_illumination_reference(scene, tracer, frag, t_s, area_samples, seed)
    from suite.core.trace.raygen import ShadowRays

    n = len(frag.position)
    lights = scene.lights_at(t_s)
    min_d = shading.min_light_distance(SimpleNamespace(extent=scene_extent(scene)))
    position = np.ascontiguousarray(frag.position, np.float64)
    normal = np.ascontiguousarray(frag.normal, np.float64)
    geo_normal = np.ascontiguousarray(frag.geo_normal, np.float64)
    vis = np.zeros((n, len(lights)), bool)
    shift = getattr(tracer, "shift", None)
    soa = bool(getattr(tracer, "soa_origins", False))
    local = hasattr(tracer, "occluded_local")
    for c0 in range(0, n if len(lights) else 0, DIRECT_CHUNK_RAYS):
        rays = ShadowRays(position, geo_normal, np.arange(c0, min(c0 + DIRECT_CHUNK_RAYS, n)), shift, soa)
        for li, light in enumerate(lights):
            o, d, length, pixel = rays.toward(light.position, shading.SHADOW_TMAX_SCALE)
            if local:
                occ = tracer.occluded_local(o, d, length)
            else:   # a tracer outside the suite's hierarchy: world-space rays, as point_light_visibility sends them
                o_world = (o.T if soa else o).astype(np.float64) + (0.0 if shift is None else shift)
                occ = tracer.occluded(o_world, d, 0.0, length)
            vis[pixel, li] = ~occ
    out = np.empty((n, 3), np.float32)
    light_pos = np.array([lt.position for lt in lights], np.float64).reshape(-1, 3)
    light_int = np.array([lt.intensity for lt in lights], np.float64).reshape(-1, 3)
    kernels.jit()["_shade_point_lights"](position, normal, light_pos, light_int, vis, float(min_d ** 2), out)
    if any(m.is_emissive for m in scene.materials):
        area = shading.AreaLights(scene, t_s)
        if len(area):
            g = _fragment_gbuffer(frag)
            out = out + shading.area_light_radiance(g, area, tracer, samples=area_samples, seed=seed,
                                                    min_distance=min_d).reshape(n, 3)
    return out


DIRECT_CHUNK_RAYS = 1 << 20    # shadow rays per light and query (the suite's point_light_visibility chunk_rays)

_extent_cache: list = []       # [(scene, extent)] of the last scene


def scene_extent(scene) -> float:
    """``scene.extent`` (the rest positions' box diagonal, fixed per scene; a pass over every vertex) once per
    scene: the light clamp distance and Algorithm 1's corner offset scale with it."""
    if not _extent_cache or _extent_cache[0][0] is not scene:
        _extent_cache[:] = [(scene, float(scene.extent))]
    return _extent_cache[0][1]


def _fragment_gbuffer(frag: Fragments):
    n = len(frag.position)
    col = lambda a: np.ascontiguousarray(a, np.float64).reshape(n, 1, -1)  # noqa: E731
    return SimpleNamespace(depth=np.zeros((n, 1)), valid=np.ones((n, 1), bool), position=col(frag.position),
                           normal=col(frag.normal), geo_normal=col(frag.geo_normal), albedo=np.ones((n, 1, 3)),
                           emission=np.zeros((n, 1, 3)))


def direct_illumination_reference(scene, tracer, frag: Fragments, t_s: float, area_samples: int,
                                  seed: int) -> np.ndarray:
    """:func:`direct_illumination` through :func:`suite.core.shading.compose_direct` itself (the device path, and
    the reference of the host one)."""
    n = len(frag.position)
    return shading.compose_direct(shading, scene, _fragment_gbuffer(frag), tracer, t_s, area_samples,
                                  seed).reshape(n, 3)


def path_trace(scene, tracer, frag: Fragments, t_s: float, spp: int, max_depth: int, rr_depth: int, rng):
    """Path tracing of every fragment (§4.4): ``spp`` paths per fragment, next-event estimation at every vertex,
    cosine-sampled Lambertian bounces, Russian roulette from vertex ``rr_depth`` on. ``max_depth`` counts
    vertices as Mitsuba does (2 = direct light only). Every material is shaded as Lambertian with its albedo.
    Returns the primary fragments' *demodulated* incident illumination (radiance / albedo, without their
    emission) and the first two moments of its luminance per fragment.

    Next-event estimation at the primary fragment takes every light (:func:`direct_illumination`, the suite's
    kernels; ``spp`` area-light samples), at later vertices one light (:class:`LightSampler`). Differs from the
    thesis (§4.4: "every hitpoint at the path is connected with shadow ray to randomly selected light source"):
    with the Quake levels' ~100 point lights, one light per primary fragment leaves heavy-tailed noise (the
    direct light comes from rare bright samples) that the layered SVGF, without the thesis's temporal
    accumulation, rejects through its luminance edge-stopping; the denoised layers came out about half as
    bright as the reference (tests/methods/layered_pvs/test_radiance.py).

    The random numbers are counter-based: the six of a bounce of row ``r`` (RR, the direction's two, the light's
    choice and its point's two) are the PCG hash of (r, seed) and the dimension ``8 * depth + j``
    (:func:`_path_numbers`), the device kernel's, so both take the same paths. The paths are split into
    :data:`PATH_PARTS` parts (contiguous row ranges; a row's numbers do not depend on its part, so neither does the
    result on how the parts are scheduled). Each part's bounces run as
    compiled passes over its wavefront (:mod:`methods.layered_pvs.kernels`) with the bits of
    :func:`path_trace_reference`, which runs the same parts one after the other. On a host tracer the parts and
    the primary fragments' direct lighting run on their own threads that take turns at the tracer (one query at
    a time, under a lock: one stream of rays, as the raw backend traces them), so one thread's shading passes
    (compiled, the GIL released) overlap another's queries; more threads than cores, so each runs as a
    :meth:`SerialTracer.part` (the query keeps a core of its own). The direct light is added last, so the sums do
    not depend on the order the threads ran in.

    On a Dr.Jit tracer (``tracer.device``) the paths run as device kernels instead
    (:func:`methods.layered_pvs.device.path_samples`: the same estimator and random numbers, in float32 where the
    device's cosine-weighted direction is, so the illumination agrees with the host passes' to rounding up to the
    rare path that a last-bit difference sends elsewhere, not bit for bit)."""
    n = len(frag.position)
    lights = LightSampler(scene, t_s)
    if n == 0 or max_depth < 2 or len(lights) == 0:
        return np.zeros((n, 3), np.float32), np.zeros(n), np.zeros(n)
    seed = int(rng.integers(1 << 31))
    device = getattr(tracer, "device", None)
    if device is not None:
        # A Dr.Jit tracer: the direct light and the paths as device kernels (the same estimators and samples); the
        # moments come back.
        from methods.layered_pvs import device as layered_device

        g = layered_device.fragment_gbuffer(device, frag)  # the fragments go up once, for both
        direct = layered_device.direct_light(device, scene, frag, t_s, max(int(spp), 1), seed, g=g)
        sample = layered_device.path_samples(device, frag, lights, spp, max_depth, rr_depth,
                                             int(rng.integers(1 << 31)), position=g.position)
        return layered_device.path_moments(device, sample, direct, n, spp)
    from concurrent.futures import ThreadPoolExecutor

    total = n * spp
    sample = np.zeros((total, 3))
    parts = _path_parts(total)
    shared = (scene, frag, t_s, spp, max_depth, rr_depth, lights, sample, int(rng.integers(1 << 31)))

    serial = SerialTracer(tracer, threading.Lock())

    def direct_light():
        try:
            with serial.part():
                return direct_illumination(scene, serial, frag, t_s, max(int(spp), 1), seed)
        finally:
            serial.queried.set()

    def paths(part):
        with serial.part():
            _part_paths(serial, *shared, *part)

    with ThreadPoolExecutor(max_workers=len(parts)) as pool:
        pending_direct = pool.submit(direct_light)
        # The parts' set-up (gathers and random numbers, holding the GIL) waits until the backend traces the
        # direct light's first rays: started together, it held those rays back by about 15 ms.
        serial.queried.wait()
        pending = [pool.submit(paths, part) for part in parts[1:]]
        paths(parts[0])
        direct = pending_direct.result()
        for f in pending:
            f.result()
    # The primary fragment's direct light last: the same sums whatever order the parts ran in.
    illum, m1, m2 = np.empty((n, 3), np.float32), np.empty(n), np.empty(n)
    kernels.jit()["_path_moments"](sample, np.ascontiguousarray(direct, np.float64), n, spp, illum, m1, m2)
    return illum, m1, m2


# Parts of the path tracer's wavefront (row ranges; a row's random numbers do not depend on its part): while one
# part's rays are traced the others shade, so the tracer finds a part ready more often the more there are, until the
# threads' switching costs more than it saves. Measured on the 2-core machine (Embree, 480x270, 4 layers, stage
# against the raw replay of its rays): living_room 0.68 / 0.75 / 0.83 / 0.77 / 0.72 with 2 / 3 / 4 / 6 / 8 parts,
# Dabrovic Sponza 0.82 with 2 and 0.93 with 4.
PATH_PARTS = 4


def _path_parts(total: int) -> list:
    """[(first row, end row)]: the wavefront's rows in :data:`PATH_PARTS` contiguous ranges (one when there are
    fewer rows than parts)."""
    count = max(1, min(PATH_PARTS, total))
    bounds = np.linspace(0, total, count + 1).astype(np.int64)
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _path_numbers(rows: np.ndarray, seed: int, depth: int, first: int, count: int) -> np.ndarray:
    """(M, ``count``) float64: the random numbers ``first .. first + count - 1`` of the bounce at ``depth`` of the
    wavefront ``rows`` (0: Russian roulette, 1-2: the direction, 3: the light's choice, 4-5: the point on it): the PCG
    hash of (row, seed) and dimension ``8 * depth + j`` (:func:`suite.core.rng.hashed_uniforms`), which the device
    kernel draws in the row's lane."""
    dims = 8 * int(depth) + int(first) + np.arange(int(count))
    return hashed_uniforms(np.ascontiguousarray(rows, np.int64), pcg_np(int(seed) & 0xFFFFFFFF), dim_hashes(dims))


def _path_moments_reference(sample, direct, n: int, spp: int):
    """(mean illumination float32, first and second moments of its luminance) per fragment, the direct light
    (per fragment, taken as float64) added to each of its ``spp`` samples (rows ``k * n + i``): the numpy
    expressions of :func:`.kernels._path_moments`, the samples summed in their order and the luminance
    ``(0.2126 r + 0.7152 g) + 0.0722 b``."""
    per = sample.reshape(spp, n, 3) + direct.astype(np.float64)[None]
    lum = (per[..., 0] * 0.2126 + per[..., 1] * 0.7152) + per[..., 2] * 0.0722
    illum, m1, m2 = per[0].copy(), lum[0].copy(), lum[0] * lum[0]
    for k in range(1, spp):
        illum += per[k]
        m1 += lum[k]
        m2 += lum[k] * lum[k]
    return (illum / spp).astype(np.float32), m1 / spp, m2 / spp


def _part_paths(tracer, scene, frag: Fragments, t_s: float, spp: int, max_depth: int, rr_depth: int, lights,
                sample, seed: int, first: int, end: int) -> None:
    """The bounces of the wavefront rows ``first:end`` (row = sample * n + fragment), their contributions added to
    ``sample`` (rows of other parts are not touched); ``seed``: the paths' (:func:`_path_numbers`)."""
    from suite.core.pipeline import local_rays, trace_local

    n = len(frag.position)
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)
    shift = getattr(tracer, "shift", None)
    shift64 = np.zeros(3) if shift is None else np.asarray(shift, np.float64)
    kern = kernels.jit()
    offset = kernels.OFFSET
    light_args = lights.kernel_args()
    # The part's wavefront shrinks in place: its buffers are allocated once for every path (the compiled passes
    # compact into them, a row never moving up); rows stay unique, so contributions are added without conflicts.
    total = end - first
    rows = np.arange(first, end)
    thr = np.ones((total, 3))          # demodulated: the primary vertex's albedo is left out
    frag_rows = rows % n
    p = np.take(frag.position, frag_rows, axis=0)  # about 4x faster than fancy indexing of (N, 3) rows
    ng = np.take(frag.geo_normal, frag_rows, axis=0)
    ns = np.take(frag.normal, frag_rows, axis=0)
    o64, d64 = np.empty((total, 3)), np.empty((total, 3))
    d32 = np.empty((total, 3), np.float32)
    prim, u, v = np.empty(total, np.int32), np.empty(total, np.float32), np.empty(total, np.float32)
    sel_rows, sel_tmax32 = np.empty(total, np.int64), np.empty(total, np.float32)
    sel_o64, sel_d32 = np.empty((total, 3)), np.empty((total, 3), np.float32)
    sel_contrib = np.empty((total, 3))
    no_rr = np.zeros(0)
    m = total
    depth = 1
    while m and depth + 1 < max_depth:
        # Russian roulette, then a cosine-weighted bounce (its pdf cancels cos/pi; the albedo remains).
        use_rr = depth >= rr_depth
        rn = _path_numbers(rows[:m], seed, depth, 0 if use_rr else 1, 3 if use_rr else 2)
        u_rr = np.ascontiguousarray(rn[:, 0]) if use_rr else no_rr
        m = kern["_bounce"](rows[:m], ns, ng, p, thr[:m], use_rr, u_rr, np.ascontiguousarray(rn[:, -2:]), shift64,
                            *offset, rows, thr, o64, d64, d32)
        if m == 0:
            break
        # The rays are put in the tracing frame here, outside the lock a shared tracer is queried under. The float64
        # origins are rounded to float32 there, in the frame the offset is sized for: rounded in world coordinates
        # first, an origin far from the frame's centre falls back onto its surface.
        hits = trace_local(tracer, local_rays(tracer, o64[:m], d32[:m]), o64[:m], d32[:m])
        m = kern["_compact_hits"](hits.prim, hits.u, hits.v, rows[:m], o64[:m], d64[:m], thr[:m], prim, u, v, rows,
                                  o64, d64, thr)
        if m == 0:
            break
        p, ng_raw, ns_raw, alb, _ = surface_attributes(scene, positions, normals, prim[:m], u[:m], v[:m], o64[:m],
                                                       d64[:m])
        # Next-event estimation towards one light (the numbers of the bounce's depth).
        nee = _path_numbers(rows[:m], seed, depth, 3, 3)
        u_sel, u2 = np.ascontiguousarray(nee[:, 0]), np.ascontiguousarray(nee[:, 1:])
        depth += 1
        ng, ns = np.empty((m, 3)), np.empty((m, 3))
        k = kern["_shade_vertex"](rows[:m], p, ng_raw, ns_raw, alb, d64[:m], thr[:m], u_sel, u2, *light_args, shift64,
                                  *offset, SHADOW_TMAX_SCALE, ng, ns, thr, sel_rows, sel_o64, sel_d32, sel_tmax32,
                                  sel_contrib)
        if k:
            query = local_rays(tracer, sel_o64[:k], sel_d32[:k], sel_tmax32[:k])
            occ = tracer.occluded(sel_o64[:k], sel_d32[:k], 0.0, sel_tmax32[:k]) if query is None \
                else tracer.occluded_local(*query)
            kern["_add_unoccluded"](sample, sel_rows[:k], sel_contrib[:k], np.asarray(occ, np.bool_))


def path_trace_reference(scene, tracer, frag: Fragments, t_s: float, spp: int, max_depth: int, rr_depth: int, rng):
    """:func:`path_trace` as whole-array numpy expressions per bounce, its parts one after the other (the reference
    its compiled passes, :mod:`methods.layered_pvs.kernels`, and its scheduling are tested against: the same bits
    from the same generator)."""
    n = len(frag.position)
    lights = LightSampler(scene, t_s)
    if n == 0 or max_depth < 2 or len(lights) == 0:
        return np.zeros((n, 3), np.float32), np.zeros(n), np.zeros(n)
    direct = direct_illumination(scene, tracer, frag, t_s, max(int(spp), 1), int(rng.integers(1 << 31)))
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)
    shift = getattr(tracer, "shift", None)
    total = n * spp
    sample = np.zeros((total, 3))
    seed = int(rng.integers(1 << 31))
    for first, end in _path_parts(total):
        # One wavefront per part (row = sample * n + fragment); rows stay unique within it, so contributions are
        # added by plain fancy indexing.
        rows = np.arange(first, end)
        p, ng, ns = frag.position[rows % n], frag.geo_normal[rows % n], frag.normal[rows % n]
        thr = np.ones((len(rows), 3))          # demodulated: the primary vertex's albedo is left out
        depth = 1
        while len(rows) and depth + 1 < max_depth:
            m = len(rows)
            # Russian roulette, then a cosine-weighted bounce (its pdf cancels cos/pi; the albedo remains).
            if depth >= rr_depth:
                q = np.minimum(thr.max(axis=1), 0.95)
                live = _path_numbers(rows, seed, depth, 0, 1)[:, 0] < q
                thr = thr / np.maximum(q, 1e-12)[:, None]
            else:
                live = np.ones(m, bool)
            d_new = _cosine_hemisphere(ns, _path_numbers(rows, seed, depth, 1, 2))
            live &= _dot(d_new, ng) > 0
            if not live.any():
                break
            rows, p, ng, ns, thr, d_new = rows[live], p[live], ng[live], ns[live], thr[live], d_new[live]
            o = offset_ray_origin(p, ng, shift)
            hits = tracer.intersect(o, d_new.astype(np.float32))  # float64 origins: rounded in the tracing frame
            hit = hits.prim >= 0
            rows, o, d_new, thr = rows[hit], o[hit], d_new[hit], thr[hit]
            if len(rows) == 0:
                break
            p2, ng2, ns2, alb2, _ = surface_attributes(scene, positions, normals, hits.prim[hit], hits.u[hit],
                                                       hits.v[hit], o, d_new)
            ng, ns, _ = _facing(ng2, ns2, d_new)
            thr = thr * alb2
            p = p2
            # Next-event estimation towards one light (the numbers of the bounce's depth).
            nee = _path_numbers(rows, seed, depth, 3, 3)
            depth += 1
            wi, dist, wl, ok = lights.sample(p, nee[:, 0], nee[:, 1:])
            cos_x = _dot(wi, ns)
            ok &= cos_x > 0
            if ok.any():
                sel = np.nonzero(ok)[0]
                side = np.where((_dot(wi[sel], ng[sel]) >= 0)[:, None], ng[sel], -ng[sel])
                o = offset_ray_origin(p[sel], side, shift)
                seg = np.linalg.norm(p[sel] + wi[sel] * dist[sel, None] - o, axis=1)
                occ = tracer.occluded(o, wi[sel].astype(np.float32), 0.0,
                                      (seg * SHADOW_TMAX_SCALE).astype(np.float32))
                lit = sel[~occ]
                sample[rows[lit]] += thr[lit] * wl[lit] * (cos_x[lit] / np.pi)[:, None]
    return _path_moments_reference(sample, direct, n, spp)


# ------------------------------------------------------------------------------------------ SVGF with layers

def spatial_variance(illum: np.ndarray, valid: np.ndarray, sample_variance: np.ndarray) -> np.ndarray:
    """Luminance variance per fragment for SVGF's edge-stopping: the larger of the sample variance of the mean
    (from the per-fragment moments) and the 3x3 spatial variance within the fragment's layer. SVGF falls back to a
    spatial estimate while a pixel has no temporal history; every update here is such a frame (no temporal
    accumulation), and with few samples the moments alone often read 0."""
    lum = illum @ np.array([0.2126, 0.7152, 0.0722])
    v = valid.astype(np.float64)
    pad = lambda a: np.pad(a, ((0, 0), (1, 1), (1, 1)))  # noqa: E731
    lp, l2p, vp = pad(lum * v), pad(lum * lum * v), pad(v)
    h, w = valid.shape[1:]
    s1 = sum(lp[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    s2 = sum(l2p[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    n = sum(vp[:, dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    mean = s1 / np.maximum(n, 1)
    var = np.maximum(s2 / np.maximum(n, 1) - mean * mean, 0.0)
    return np.where(valid, np.maximum(var, sample_variance), 0.0)


_svgf_kernel = None


def _svgf():
    global _svgf_kernel
    if _svgf_kernel is None:
        import numba

        # error_model="numpy": a weight sum that underflows gives inf/nan here instead of raising (guarded below).
        # parallel: the rows on the cores, every output fragment written by one iteration (the same bits as one
        # thread); rows taken alternately from the image's two halves, so that both cores meet its sky and its
        # depth complexity alike. Grids are (H, W, L[, 3]): a tap's search through the layers reads neighbours.
        @numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
        def atrous(col, var, pos, nrm, valid, depth, step, pix_angle, shift_scale, sigma_l, sigma_n, out_col,
                   out_var):
            H, W, L = valid.shape
            h = (1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16)
            int_n = int(sigma_n) if sigma_n == math.floor(sigma_n) and 0 < sigma_n <= 1024 else 0
            half = (H + 1) // 2
            radius = np.empty((5, 5))  # each tap's distance from the centre in taps
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    radius[dy + 2, dx + 2] = math.sqrt(float(dx * dx + dy * dy))
            for i in numba.prange(H):
                y = i // 2 if i % 2 == 0 else half + i // 2
                for x in range(W):
                    for k in range(L):
                        if not valid[y, x, k]:
                            continue
                        lc = 0.2126 * col[y, x, k, 0] + 0.7152 * col[y, x, k, 1] + 0.0722 * col[y, x, k, 2]
                        sd = math.sqrt(max(var[y, x, k], 0.0))
                        foot = depth[y, x, k] * pix_angle
                        wsum = 0.0
                        vsum = 0.0
                        c0 = 0.0
                        c1 = 0.0
                        c2 = 0.0
                        for dy in range(-2, 3):
                            yy = y + dy * step
                            if yy < 0 or yy >= H:
                                continue
                            for dx in range(-2, 3):
                                xx = x + dx * step
                                if xx < 0 or xx >= W:
                                    continue
                                # §4.4.1: among the fragments at this tap, the one closest to the centre
                                # fragment's plane shifted along its normal (towards the camera) by a distance
                                # growing with the camera distance and the tap's screen distance.
                                shift = shift_scale * foot * radius[dy + 2, dx + 2] * step
                                best = -1
                                best_d = 1e300
                                best_pd = 0.0
                                for m in range(L):
                                    if not valid[yy, xx, m]:
                                        break
                                    pd = (nrm[y, x, k, 0] * (pos[yy, xx, m, 0] - pos[y, x, k, 0])
                                          + nrm[y, x, k, 1] * (pos[yy, xx, m, 1] - pos[y, x, k, 1])
                                          + nrm[y, x, k, 2] * (pos[yy, xx, m, 2] - pos[y, x, k, 2]))
                                    dd = abs(pd - shift)
                                    if dd < best_d:
                                        best_d = dd
                                        best = m
                                        best_pd = pd
                                if best < 0:
                                    continue
                                ln = 0.2126 * col[yy, xx, best, 0] + 0.7152 * col[yy, xx, best, 1] \
                                    + 0.0722 * col[yy, xx, best, 2]
                                ndot = (nrm[y, x, k, 0] * nrm[yy, xx, best, 0] + nrm[y, x, k, 1] * nrm[yy, xx, best, 1]
                                        + nrm[y, x, k, 2] * nrm[yy, xx, best, 2])
                                # max(ndot, 0) ** sigma_n, without the power where it is exactly 1 (half the taps:
                                # equal normals) or 0; a zero weight adds nothing, so such a tap is skipped. An
                                # integer exponent (the default 128) by squarings rather than pow.
                                if ndot <= 0.0:
                                    continue
                                if ndot == 1.0:
                                    wn = 1.0
                                elif int_n > 0:
                                    wn, base, e = 1.0, ndot, int_n
                                    while e:
                                        if e & 1:
                                            wn *= base
                                        base *= base
                                        e >>= 1
                                else:
                                    wn = ndot ** sigma_n
                                dist_px = radius[dy + 2, dx + 2] * step
                                # The plane-distance and luminance weights exp(-a) exp(-b) as one exp(-(a + b)).
                                wzl = math.exp(-(abs(best_pd) / (foot * (dist_px + 1.0) + 1e-12)
                                                 + abs(lc - ln) / (sigma_l * sd + 1e-10)))
                                wgt = h[dy + 2] * h[dx + 2] * wn * wzl
                                wsum += wgt
                                vsum += wgt * wgt * var[yy, xx, best]
                                c0 += wgt * col[yy, xx, best, 0]
                                c1 += wgt * col[yy, xx, best, 1]
                                c2 += wgt * col[yy, xx, best, 2]
                        if wsum > 1e-150:
                            out_col[y, x, k, 0] = c0 / wsum
                            out_col[y, x, k, 1] = c1 / wsum
                            out_col[y, x, k, 2] = c2 / wsum
                            out_var[y, x, k] = vsum / (wsum * wsum)
                        else:
                            out_col[y, x, k, :] = col[y, x, k, :]
                            out_var[y, x, k] = var[y, x, k]

        _svgf_kernel = atrous
    return _svgf_kernel


def scatter_fragments(values: np.ndarray, index, shape, dim: int) -> np.ndarray:
    """Per-fragment ``values`` placed into an (L, H, W[, dim]) float64 grid (zero where no fragment)."""
    out = np.zeros(tuple(shape) + ((dim,) if dim else ()), np.float64)
    out[index] = values
    return out


def denoise_fragments(view: LayerView, layers: Layers, frag: Fragments, illum, m1, m2, spp: int,
                      iterations: int, device=None) -> np.ndarray:
    """The layered SVGF (§4.4.1) applied to ``path_trace``'s output: per-fragment demodulated illumination
    (N, 3) after ``iterations`` à-trous passes (unchanged with 0 passes or no fragment). With a Dr.Jit ``device``
    (a Mitsuba llvm/cuda tracer's) the passes run as its kernel (:mod:`methods.layered_pvs.device`, in float32: the
    same values to float32 rounding; the grids are counted copies), and from fragments that device made the kernel's
    tables are built there (:func:`methods.layered_pvs.device.denoise`: only the fragments' light, variance and depth
    go up)."""
    if iterations <= 0 or len(frag.position) == 0:
        return np.asarray(illum, np.float64)
    shape = layers.prim.shape
    grid = lambda vals, dim: scatter_fragments(vals, frag.index, shape, dim)  # noqa: E731
    var = np.maximum(m2 - m1 * m1, 0.0) / max(int(spp), 1)
    pix_angle = 2 * math.tan(math.radians(view.fov_deg) / 2) / view.width
    if device is not None:
        from methods.layered_pvs import device as layered_device

        if layered_device.twins(frag, device) is not None:  # fragments this device made: the tables built there
            out = layered_device.denoise(device, layers, frag, illum, var, pix_angle, iterations)
            return out.astype(np.float32).astype(np.float64)
    var_g = spatial_variance(grid(illum, 3), layers.valid, grid(var, 0))
    # svgf_layers's grids, but the three-channel ones scattered straight into the kernel's (H, W, L) layout rather
    # than transposed from (L, H, W) (about 15 ms an update at 480x270 with 4 layers): the same values.
    k, y, x = frag.index
    pixel_index, pixel_shape = (y, x, k), shape[1:] + shape[:1]
    pixel_grid = lambda vals: scatter_fragments(vals, pixel_index, pixel_shape, 3)  # noqa: E731
    if device is not None:
        from methods.layered_pvs.device import svgf_passes as passes

        passes = partial(passes, device)
    else:
        passes = _svgf_passes
    out = passes(pixel_grid(illum), pixel_major(var_g, np.float64), pixel_grid(frag.position),
                 pixel_grid(frag.normal), pixel_major(layers.valid, np.bool_),
                 pixel_major(np.where(layers.valid, layers.t, 0.0), np.float64), pix_angle, iterations)
    return out[pixel_index].astype(np.float32).astype(np.float64)


def svgf_layers(illum, variance, position, normal, valid, depth, pix_angle: float, iterations: int = 5,
                shift_scale: float = 1.0, sigma_l: float = 4.0, sigma_n: float = 128.0):
    """SVGF's à-trous wavelet filter (5x5 B3 kernel, step 2^i, ``iterations`` passes; edge-stopping on normal,
    plane distance and luminance against the variance) extended to layers as §4.4.1 describes. Inputs are
    (L, H, W[, 3]) grids; returns the filtered illumination (L, H, W, 3) float32.

    Differs from the thesis: no temporal accumulation (updates are ~180 ms apart), so the variance comes from the
    per-fragment sample moments only, and it is not pre-blurred."""
    col = _svgf_passes(pixel_major(illum, np.float64), pixel_major(variance, np.float64),
                       pixel_major(position, np.float64), pixel_major(normal, np.float64), pixel_major(valid, np.bool_),
                       pixel_major(np.where(valid, depth, 0.0), np.float64), pix_angle, iterations, shift_scale,
                       sigma_l, sigma_n)
    return np.ascontiguousarray(np.moveaxis(col, 2, 0), np.float32)


def pixel_major(a, dtype) -> np.ndarray:
    """An (L, H, W[, C]) layer grid in the SVGF kernel's layout, (H, W, L[, C]): a pixel's fragments side by side."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(a), 0, 2), dtype)


def _svgf_passes(col, var, pos, nrm, val, dep, pix_angle: float, iterations: int, shift_scale: float = 1.0,
                 sigma_l: float = 4.0, sigma_n: float = 128.0) -> np.ndarray:
    """The à-trous passes of :func:`svgf_layers` on grids in the kernel's (H, W, L[, 3]) layout (float64, bool for
    ``val``); returns the filtered (H, W, L, 3) float64 illumination."""
    kern = _svgf()
    for i in range(iterations):
        out_c = np.zeros_like(col)
        out_v = np.zeros_like(var)
        kern(col, var, pos, nrm, val, dep, 1 << i, float(pix_angle), float(shift_scale), float(sigma_l),
             float(sigma_n), out_c, out_v)
        col, var = out_c, out_v
    return col
