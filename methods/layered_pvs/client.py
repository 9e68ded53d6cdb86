"""Client side of seed 002 (§4.3, Fig. 4.8, Algorithm 4.1): the PVS geometry as the client holds it, depth peeling
of it from the update's viewpoint (with or without triangle subsets, §4.5.1), and the reprojection of the layers
into each client frame.

The client has no GPU rasteriser here: "rasterising the PVS" is ray casting it with Embree (one primary ray per
pixel centre, the same sample positions a rasteriser uses), which gives the same depth layers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.core.gbuffer import camera_rays, project
from suite.core.trace.base import Hits, as_rays
from suite.core.trace.embree import build_embree_scene

from methods.layered_pvs import kernels, packing
from methods.layered_pvs.server import LayerView, Layers, past, peel


class Geometry:
    """Triangles (T, 3, 3) float32 the client can cast rays against; hit ``prim`` = row of ``triangles``."""

    def __init__(self, triangles: np.ndarray, ids: np.ndarray | None = None):
        self.triangles = np.ascontiguousarray(triangles, np.float32).reshape(-1, 3, 3)
        self.ids = None if ids is None else np.asarray(ids, np.int64)   # subset rows -> PVS rows
        if len(self.triangles):
            lo, hi = self.triangles.reshape(-1, 3).min(0), self.triangles.reshape(-1, 3).max(0)
            self.shift = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
        else:
            self.shift = np.zeros(3)
        local = (self.triangles.astype(np.float64) - self.shift).astype(np.float32)
        self.scene = build_embree_scene(local) if len(local) else None
        self.rays = 0

    def intersect(self, origins, dirs, tmin=0.0) -> Hits:
        o, d, tmin_a, length = as_rays(origins, dirs, tmin, np.inf, self.shift)
        hits = self.intersect_local(o, d, length)
        hits.t += tmin_a
        return hits

    def intersect_local(self, o, d, length) -> Hits:
        """Closest hits of rays already in this geometry's frame (``as_rays`` with its ``shift``); ``t`` is measured
        from ``o``, misses read t = inf and prim = -1. Embree may overwrite ``length``."""
        n = len(d)
        self.rays += n
        if self.scene is None or n == 0:
            return Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32),
                        np.zeros(n, np.float32))
        res = self.scene.run(o, d, dists=length, output=1)
        prim = np.asarray(res["primID"], np.int64)
        t = np.asarray(res["tfar"], np.float32).copy()
        miss = prim < 0
        t[miss] = np.inf
        if self.ids is not None:
            prim = np.where(miss, -1, self.ids[np.maximum(prim, 0)])
        return Hits(t, prim, np.asarray(res["u"], np.float32), np.asarray(res["v"], np.float32))


def peel_client(triangles: np.ndarray, view: LayerView, layers: int, subsets: np.ndarray | None = None):
    """The client's depth layers of its PVS from the update's view (§4.3.1). With ``subsets`` ((L, T) bool, the
    server's triangle-subset masks, §4.5.1) layer k is peeled against the triangles of subset k only.
    Returns (Layers with PVS row ids, rays cast)."""
    o, d = camera_rays(view.pose, view.fov_deg, view.width, view.height, dtype=np.float64)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    shape = (view.height, view.width)
    if subsets is None:
        geo = Geometry(triangles)
        return peel(geo, o32, d32, layers, shape=shape), geo.rays
    t = np.full((layers,) + shape, np.inf, np.float32)
    prim = np.full((layers,) + shape, -1, np.int64)
    u = np.zeros((layers,) + shape, np.float32)
    v = np.zeros((layers,) + shape, np.float32)
    tmin = np.zeros(len(d32), np.float32)
    alive = np.ones(len(d32), bool)
    rays = 0
    for k in range(layers):
        ids = np.nonzero(subsets[k])[0] if k < len(subsets) else np.zeros(0, np.int64)
        if len(ids) == 0 or not alive.any():
            break
        geo = Geometry(triangles[ids], ids)
        idx = np.nonzero(alive)[0]
        h = geo.intersect(o32[idx], d32[idx], tmin[idx])
        rays += geo.rays
        hit = h.prim >= 0
        sel = idx[hit]
        t.reshape(layers, -1)[k, sel] = h.t[hit]
        prim.reshape(layers, -1)[k, sel] = h.prim[hit]
        u.reshape(layers, -1)[k, sel] = h.u[hit]
        v.reshape(layers, -1)[k, sel] = h.v[hit]
        alive[:] = False
        alive[sel] = True
        tmin[sel] = past(h.t[hit])
    return Layers(t, prim, u, v), rays


def triangle_subsets(layers: Layers, n_triangles: int) -> np.ndarray:
    """§4.5.1 on the server: subset k = the PVS triangles that own a fragment of layer k. Peeling layer k against
    it gives the same nearest hit past layer k-1 for every pixel (the true hit is in the subset, and nothing
    nearer exists in the whole PVS). (L, T) bool over PVS rows."""
    L = layers.prim.shape[0]
    out = np.zeros((L, n_triangles), bool)
    for k in range(L):
        p = layers.prim[k]
        out[k, p[p >= 0]] = True
    return out


@dataclass
class DecodedUpdate:
    """What the client holds after the scene update (Fig. 4.8): the view, the geometry, the layer depths and the
    packed texture with each pixel's k-th fragment in slot k (relocated back), addressed by Algorithm 4.1."""

    index: int
    view: LayerView
    geometry: Geometry
    tri_normals: np.ndarray      # (T, 3) unit geometric normals of the PVS triangles
    depth: np.ndarray            # (L, H_l, W_l) client-peeled distances (inf = no fragment)
    counts: np.ndarray           # (H_l, W_l) fragments per pixel
    layout: packing.TileLayout
    texture: np.ndarray          # (texture rows, W_l, 3) uint8, fragments relocated back
    exposure: float


@dataclass
class FrameStats:
    no_hit: int          # pixels where the current view sees no PVS triangle (sky or PVS failure)
    outside: int         # hit points outside the update's enlarged frustum
    unmatched: int       # hit points whose depth matches no layer (disocclusions, too few layers)
    filled: int          # hole pixels filled by the hole-filling variant
    rays: int


def render_frame(dec: DecodedUpdate, pose, fov_deg: float, width: int, height: int, depth_tol: float,
                 hole_fill: bool):
    """Algorithm 4.1 and §4.3.2: the PVS seen from the current pose; each visible point is projected into the
    update's view and takes the colour of the layer whose depth matches its distance there. Returns
    (rgb8 (H, W, 3), hole mask (H, W), FrameStats)."""
    o, d = camera_rays(pose, fov_deg, width, height, dtype=np.float64)
    geo = dec.geometry
    rays0 = geo.rays
    h = geo.intersect(o.astype(np.float32), d.astype(np.float32))
    n = width * height
    rgb = np.zeros((n, 3), np.uint8)
    hit = h.prim >= 0
    idx = np.nonzero(hit)[0]
    x_world = o[idx] + d[idx] * h.t[idx, None].astype(np.float64)
    view = dec.view
    xy, z = project(x_world, view.pose, view.fov_deg, view.width, view.height)
    m = len(idx)
    ix, iy, layer = np.zeros(m, np.int64), np.zeros(m, np.int64), np.zeros(m, np.int64)
    inside, matched = np.empty(m, np.bool_), np.empty(m, np.bool_)
    pix_angle = 2 * np.tan(np.radians(view.fov_deg) / 2) / view.width
    kernels.jit()["_reproject_match"](x_world, np.ascontiguousarray(xy), np.ascontiguousarray(z, np.float64),
                                      np.ascontiguousarray(h.prim[idx], np.int64), np.asarray(view.pose.position,
                                      np.float64), np.ascontiguousarray(dec.tri_normals, np.float64),
                                      np.ascontiguousarray(dec.depth), float(depth_tol), float(pix_angle),
                                      int(view.width), int(view.height), ix, iy, layer, inside, matched)
    ok = packing.fetch(dec.layout, dec.texture, ix, iy, layer, matched, idx, rgb)
    hole = np.zeros(n, bool)
    hole[idx[~ok]] = True
    filled = 0
    img = rgb.reshape(height, width, 3)
    if hole_fill and hole.any():
        img, filled = fill_holes(img, hole.reshape(height, width))
    stats = FrameStats(no_hit=int(n - len(idx)), outside=int((~inside).sum()),
                       unmatched=int((inside & ~ok).sum()), filled=filled, rays=geo.rays - rays0)
    return img, hole.reshape(height, width), stats


def fill_holes(img: np.ndarray, hole: np.ndarray, rounds: int = 64):
    """Hole filling beyond the thesis (its §7.1 suggests screen-space post-processing): hole pixels take the mean
    of their non-hole 4-neighbours, round after round (a push from the borders inwards)."""
    out = img.astype(np.float32)
    have = ~hole
    todo = int(hole.sum())
    for _ in range(rounds):
        if have.all():
            break
        pad_c = np.pad(out, ((1, 1), (1, 1), (0, 0)))
        pad_h = np.pad(have, 1).astype(np.float32)
        s = (pad_c[:-2, 1:-1] * pad_h[:-2, 1:-1, None] + pad_c[2:, 1:-1] * pad_h[2:, 1:-1, None]
             + pad_c[1:-1, :-2] * pad_h[1:-1, :-2, None] + pad_c[1:-1, 2:] * pad_h[1:-1, 2:, None])
        cnt = pad_h[:-2, 1:-1] + pad_h[2:, 1:-1] + pad_h[1:-1, :-2] + pad_h[1:-1, 2:]
        new = ~have & (cnt > 0)
        if not new.any():
            break
        out[new] = s[new] / cnt[new, None]
        have |= new
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), todo - int((~have).sum())
