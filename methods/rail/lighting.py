"""Light tracing and point-cloud shading (seed 004, RAIL §3.1-3.2, Algorithm 1 lines 3-4).

* :func:`trace_light_paths` follows light paths from the point lights and the emissive triangles and records
  every diffuse bounce: the vertices are the dart sources of §3.1 and the virtual point lights (VPLs) of §3.2.
* :func:`shade_points` sums, per sample point q, the contributions of the VPLs that q sees (one shadow ray per
  VPL·point pair, traced in batches through the suite's tracer).
* :class:`ProgressiveIrradiance` accumulates passes: E = mean of the contributions while the scene is unchanged;
  a change starts a new sequence whose first term is the previous estimate (E₀ = E, §3.2).

Units follow the suite's kernels: a point light of intensity I (W/sr) emits 4πI W; a VPL carries the flux Φ that
arrived at its surface (W, RGB) and re-emits it diffusely, I_v(ω) = Φ ρ/π cos θ_v, so the irradiance it gives a
point q at distance d is Φ ρ/π cos θ_v cos θ_q / d².
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from suite.core.gbuffer import surface_attributes
from suite.core.trace.robust import offset_ray_origin

INV_PI = 1.0 / np.pi
# Shadow rays stop this fraction short of the VPL (its own surface never shadows it).
SHADOW_TMAX_SCALE = 1.0 - 1e-4
# At most this many VPL·point pairs per tracer call.
PAIR_BATCH = 1 << 19


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) perpendicular to unit normals ``n`` (Duff et al. 2017, branchless)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=-1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=-1)
    return t, s


def cosine_directions(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions (N, 3) in the hemispheres of unit normals ``n``."""
    t, s = orthonormal_basis(n)
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    d = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * s + z[:, None] * n
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass
class PathVertices:
    """Diffuse bounces of light paths: the VPLs (and §3.1's dart sources)."""

    position: np.ndarray   # (V, 3) float64
    normal: np.ndarray     # (V, 3) float64 geometric normal on the side the light came from
    albedo: np.ndarray     # (V, 3) float64 diffuse reflectance
    flux: np.ndarray       # (V, 3) float64 flux that arrived (W)
    bounce: np.ndarray     # (V,) int32, 1 = first surface hit
    face: np.ndarray       # (V,) int32

    def __len__(self) -> int:
        return int(len(self.position))


def scene_cones(positions: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point light: the unit axis toward the scene's bounding sphere and the cosine of the cone that holds
    it (-1: the light is inside the sphere, every direction can hit). Light outside the cone never meets the
    scene, so it is not traced (distant sun and sky lights of game levels would waste almost every path)."""
    to_c = np.asarray(centre, np.float64)[None, :] - positions
    dist = np.linalg.norm(to_c, axis=1)
    axis = to_c / np.maximum(dist, 1e-30)[:, None]
    outside = dist > radius
    cos_max = np.where(outside, np.sqrt(np.maximum(0.0, 1.0 - (radius / np.maximum(dist, 1e-30)) ** 2)), -1.0)
    return axis, cos_max


def cone_directions(axis: np.ndarray, cos_max: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Uniform directions inside cones (axis, cos_max); cos_max = -1 is the whole sphere."""
    t, s = orthonormal_basis(axis)
    cos_t = 1.0 - u1 * (1.0 - cos_max)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * np.pi * u2
    return (sin_t * np.cos(phi))[:, None] * t + (sin_t * np.sin(phi))[:, None] * s + cos_t[:, None] * axis


def light_power(positions: np.ndarray, intensities: np.ndarray, area_lights,
                cone_fraction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(per-source power by luminance (S,), per-source RGB flux (S, 3)) that can reach the scene: point lights
    first (4πI times the solid-angle fraction of their cone toward the scene), then triangles."""
    point_rgb = 4.0 * np.pi * np.asarray(intensities, np.float64).reshape(-1, 3)
    if cone_fraction is not None:
        point_rgb = point_rgb * np.asarray(cone_fraction, np.float64)[:, None]
    tri_rgb = (np.pi * area_lights.area[:, None] * area_lights.radiance) if area_lights is not None and len(area_lights) \
        else np.zeros((0, 3))
    rgb = np.concatenate([point_rgb, tri_rgb])
    return rgb.mean(axis=-1), rgb


def trace_light_paths(scene, tracer, t_s: float, light_positions, light_intensities, n_paths: int,
                      max_bounces: int, rng: np.random.Generator, area_lights=None) -> PathVertices:
    """Light tracing (§3.2 "tracing a number of light paths and creating VPLs for each path vertex").

    Sources are picked in proportion to the power that can reach the scene; each path carries flux
    Φ_s / (p_s n_paths) and keeps ``flux · ρ`` after every diffuse bounce (no Russian roulette, at most
    ``max_bounces`` vertices). A point light outside the scene's bounding sphere emits only into the cone that
    holds the sphere (:func:`scene_cones`).
    """
    light_positions = np.asarray(light_positions, np.float64).reshape(-1, 3)
    lo, hi = scene.bounds()
    centre = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    axis, cos_max = scene_cones(light_positions, centre, 0.5 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo)))
    power, rgb = light_power(light_positions, light_intensities, area_lights, 0.5 * (1.0 - cos_max))
    empty = PathVertices(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                         np.zeros(0, np.int32), np.zeros(0, np.int32))
    if n_paths <= 0 or power.sum() <= 0:
        return empty
    prob = power / power.sum()
    src = rng.choice(len(prob), size=n_paths, p=prob)
    flux = rgb[src] / (prob[src, None] * n_paths)
    n_point = len(light_positions)
    origin = np.zeros((n_paths, 3))
    direction = np.zeros((n_paths, 3))
    is_point = src < n_point
    u = rng.random((n_paths, 4))
    origin[is_point] = light_positions[src[is_point]]
    k_pt = src[is_point]
    direction[is_point] = cone_directions(axis[k_pt], cos_max[k_pt], u[is_point, 0], u[is_point, 1])
    tri = ~is_point
    if tri.any():
        k = src[tri] - n_point
        a, b = u[tri, 2], u[tri, 3]
        sa = np.sqrt(a)
        w0, w1, w2 = 1.0 - sa, sa * (1.0 - b), sa * b
        v = area_lights.vertices[k]
        p = w0[:, None] * v[:, 0] + w1[:, None] * v[:, 1] + w2[:, None] * v[:, 2]
        nrm = area_lights.normal[k]
        origin[tri] = offset_ray_origin(p, nrm, getattr(tracer, "shift", None))
        direction[tri] = cosine_directions(nrm, u[tri, 0], u[tri, 1])
    # Every bounce's two random numbers of every path, drawn up front: a path's numbers depend on its index and
    # bounce only, so a ray that hits elsewhere (backends differ at their parity) changes that path alone, and the
    # generator leaves this call in the same state whatever the paths hit.
    u_bounce = rng.random((max(int(max_bounces), 0), n_paths, 2))
    positions = scene.positions_at(t_s)
    normals = scene.normals_at(t_s)
    out = []
    alive = np.arange(n_paths)
    for bounce in range(1, int(max_bounces) + 1):
        if len(alive) == 0:
            break
        # float64 origins: the tracer rounds them in its own frame, where the offset is sized (rounded in world
        # coordinates first, an origin far from the frame's centre falls back onto its surface)
        hits = tracer.intersect(origin, direction.astype(np.float32))
        ok = hits.prim >= 0
        if not ok.any():
            break
        origin, direction, flux, alive = origin[ok], direction[ok], flux[ok], alive[ok]
        prim = hits.prim[ok]
        p, ng, _, albedo, _ = surface_attributes(scene, positions, normals, prim, hits.u[ok], hits.v[ok],
                                                 origin, direction.astype(np.float64))
        ng = np.where((np.einsum("ij,ij->i", ng, direction) > 0)[:, None], -ng, ng)
        albedo = np.clip(albedo.astype(np.float64), 0.0, 1.0)
        out.append(PathVertices(p, ng, albedo, flux, np.full(len(p), bounce, np.int32), prim.astype(np.int32)))
        flux = flux * albedo
        keep = flux.max(axis=-1) > 0
        u2 = u_bounce[bounce - 1, alive]
        origin = offset_ray_origin(p, ng, getattr(tracer, "shift", None))[keep]
        direction = cosine_directions(ng[keep], u2[keep, 0], u2[keep, 1])
        flux, alive = flux[keep], alive[keep]
    if not out:
        return empty
    return PathVertices(*(np.concatenate([getattr(o, f) for o in out]) for f in
                          ("position", "normal", "albedo", "flux", "bounce", "face")))


def shade_points(points: np.ndarray, normals: np.ndarray, vpls: PathVertices, tracer,
                 clamp_m: float, batch: int = PAIR_BATCH) -> tuple[np.ndarray, dict]:
    """Irradiance (N, 3) at every point from the VPLs it sees (§3.2's second phase).

    Per pair: E += Φ ρ/π cos θ_v cos θ_q / max(d², clamp²) when both cosines are positive and the shadow ray
    from q (offset along its normal) to the VPL is unblocked. Distances under ``clamp_m`` are clamped (the usual
    many-lights bound on the 1/d² singularity; it removes energy near corners). Returns (E, counters:
    ``pairs`` = VPL·point pairs, ``rays`` = shadow rays traced).

    The pairs are summed in batches of whole VPLs against every point (at most ``batch`` pairs, at least one VPL):
    each batch's contributions per point, then the batch added to E. Their shadow rays go in steps of about
    :data:`STEP_PAIRS` pairs, pipelined (:func:`suite.core.pipeline.pipelined`): while the backend traces one step's
    rays, a worker makes the next step's (one compiled pass, :func:`_pair_rays`) and adds up a traced one's
    (:func:`_accumulate`), so the pass costs little more than its queries. The result has the bits of
    :func:`shade_points_reference` (the batches' whole-array numpy expressions): the same rays, and per point the
    same contributions added in the same order. On a tracer with a Dr.Jit device (Mitsuba llvm/cuda) the pass is one
    device kernel instead (:func:`methods.rail.device.shade_points`: the same rays and sums).
    """
    import threading
    from functools import partial

    from suite.core.pipeline import local_rays, pipelined

    E, counters, inputs = _shading_inputs(points, normals, vpls, tracer)
    if inputs is None:
        return E, counters
    q_origin, qn, v_pos, intensity = inputs
    n_pts, n_vpl = len(q_origin), len(v_pos)
    v_normal = np.ascontiguousarray(vpls.normal, np.float64)
    device = getattr(tracer, "device", None)
    if device is not None:  # a Mitsuba llvm/cuda tracer: the pass as one device kernel, its rays never leave it
        from .device import shade_points as shade_on_device

        E, counters["rays"] = shade_on_device(device, q_origin, qn, v_pos, v_normal, intensity, clamp_m,
                                              max(1, int(batch) // n_pts))
        return E, counters
    # Steps of whole VPLs (about STEP_PAIRS pairs) within the reference's batches: per point, the contributions still
    # come in VPL order, so summing the steps of a batch one after the other gives the batch's sums.
    per = max(1, int(batch) // n_pts)
    step = max(1, min(per, STEP_PAIRS // n_pts))
    steps = [(v0, min(n_vpl, v0 + step, b0 + per), min(n_vpl, v0 + step, b0 + per) == min(n_vpl, b0 + per))
             for b0 in range(0, n_vpl, per) for v0 in range(b0, min(n_vpl, b0 + per), step)]
    rays = [0] * len(steps)
    made, blocked = {}, {}
    order = threading.Condition()
    # the next step to add up, the open batch's sums, whether a step failed
    state = {"next": 0, "sums": np.zeros((n_pts, 3)), "failed": False}

    def make(k):
        v0, v1, _ = steps[k]
        m = n_pts * (v1 - v0)
        o, d, tmax = np.empty((m, 3)), np.empty((m, 3), np.float32), np.empty(m)
        q_idx, v_idx, g = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m)
        count = _pair_rays(q_origin, qn, v_pos, v_normal, v0, v1, SHADOW_TMAX_SCALE, float(clamp_m) ** 2, o, d, tmax,
                           q_idx, v_idx, g)
        rays[k] = count
        o, d, tmax = o[:count], d[:count], tmax[:count]
        made[k] = (o, d, tmax, local_rays(tracer, o, d, tmax) if count else None, q_idx[:count], v_idx[:count],
                   g[:count])

    def trace(k):
        o, d, tmax, query = made[k][:4]
        if rays[k]:
            blocked[k] = tracer.occluded(o, d, 0.0, tmax) if query is None else tracer.occluded_local(*query)

    def finish(k):
        q_idx, v_idx, g = made.pop(k)[4:]
        with order:  # in step order (once every step is traced, finishes run on two threads)
            order.wait_for(lambda: state["next"] == k or state["failed"])
            if state["failed"]:  # an earlier step's error, which the pipeline raises
                return
            try:
                if rays[k]:
                    _accumulate(np.ascontiguousarray(blocked.pop(k), np.bool_), q_idx, v_idx, g, intensity,
                                state["sums"])
                if steps[k][2]:  # the batch's last step: its sums go to E
                    E[...] += state["sums"]
                    state["sums"][...] = 0.0
            except BaseException:
                state["failed"] = True
                raise
            finally:
                state["next"] = k + 1
                order.notify_all()

    pipelined([(partial(make, k), partial(trace, k), partial(finish, k)) for k in range(len(steps))])
    counters["rays"] = int(sum(rays))
    return E, counters


# VPL·point pairs per pipeline step of shade_points (whole VPLs): small enough that the backend starts at once and
# the last step's sums are quick, large enough that a step's Python costs little beside its query.
STEP_PAIRS = 1 << 15


@numba.njit(cache=True, nogil=True)
def _pair_rays(q_origin, qn, v_pos, v_normal, v0, v1, tmax_scale, clamp2, o, d, tmax, q_idx, v_idx, g):
    """The shadow rays of the pairs (every point, VPLs v0:v1) whose cosines are both positive, in
    :func:`shade_points_reference`'s order (point-major, as ``np.nonzero``): origin, float32 direction, tmax, the
    pair and its geometry term ``cos θ_q cos θ_v / max(d², clamp²)``, with the reference's float64 operations in
    their order (:func:`_dot3`'s sums). Returns how many."""
    count = 0
    for i in range(q_origin.shape[0]):
        for j in range(v0, v1):
            tx = v_pos[j, 0] - q_origin[i, 0]
            ty = v_pos[j, 1] - q_origin[i, 1]
            tz = v_pos[j, 2] - q_origin[i, 2]
            d2 = (tx * tx + tz * tz) + ty * ty
            dist = np.sqrt(max(d2, 1e-300))
            wx, wy, wz = tx / dist, ty / dist, tz / dist
            cos_q = (wx * qn[i, 0] + wz * qn[i, 2]) + wy * qn[i, 1]
            cos_v = -((wx * v_normal[j, 0] + wz * v_normal[j, 2]) + wy * v_normal[j, 1])
            if not (cos_q > 0.0 and cos_v > 0.0):
                continue
            o[count, 0], o[count, 1], o[count, 2] = q_origin[i, 0], q_origin[i, 1], q_origin[i, 2]
            d[count, 0], d[count, 1], d[count, 2] = np.float32(wx), np.float32(wy), np.float32(wz)
            tmax[count] = dist * tmax_scale
            q_idx[count], v_idx[count] = i, j
            g[count] = cos_q * cos_v / max(d2, clamp2)
            count += 1
    return count


@numba.njit(cache=True, nogil=True)
def _accumulate(blocked, q_idx, v_idx, g, intensity, sums):
    """``sums[q] += g * I_v`` for every unblocked pair, in ray order (``np.bincount``'s sums, channel by channel)."""
    for r in range(g.shape[0]):
        if blocked[r]:
            continue
        i, j = q_idx[r], v_idx[r]
        for c in range(3):
            sums[i, c] += g[r] * intensity[j, c]


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over the last axis summed as (x + z) + y: ``np.einsum``'s order for three terms here, written
    out so that the compiled pass (:func:`_pair_rays`) can follow it."""
    return (a[..., 0] * b[..., 0] + a[..., 2] * b[..., 2]) + a[..., 1] * b[..., 1]


def _shading_inputs(points, normals, vpls: PathVertices, tracer):
    """(E = 0 per point, counters, inputs) of a shading pass; inputs, None without points or VPLs: the points' ray
    origins (offset along their normals, float64 world space), their normals, the VPLs' offset positions and their
    intensity over cos θ_v (I_v / cos θ_v = Φ ρ/π), contiguous."""
    n_pts, n_vpl = len(points), len(vpls)
    E = np.zeros((n_pts, 3), np.float64)
    counters = {"pairs": n_pts * n_vpl, "rays": 0}
    if n_pts == 0 or n_vpl == 0:
        return E, counters, None
    shift = getattr(tracer, "shift", None)
    qn = np.ascontiguousarray(normals, np.float64)
    q_origin = np.ascontiguousarray(offset_ray_origin(np.asarray(points, np.float64), qn, shift))
    v_pos = np.ascontiguousarray(offset_ray_origin(vpls.position, vpls.normal, shift))
    return E, counters, (q_origin, qn, v_pos, np.ascontiguousarray(vpls.flux * vpls.albedo * INV_PI))


def shade_points_reference(points: np.ndarray, normals: np.ndarray, vpls: PathVertices, tracer,
                           clamp_m: float, batch: int = PAIR_BATCH) -> tuple[np.ndarray, dict]:
    """:func:`shade_points` as whole-array numpy expressions per batch, one batch after the other (the reference
    its compiled passes and pipeline are tested against)."""
    E, counters, inputs = _shading_inputs(points, normals, vpls, tracer)
    if inputs is None:
        return E, counters
    q_origin, qn, v_pos, intensity = inputs
    n_pts, n_vpl = len(q_origin), len(v_pos)
    per = max(1, int(batch) // n_pts)
    for v0 in range(0, n_vpl, per):
        vs = slice(v0, min(n_vpl, v0 + per))
        to_v = v_pos[None, vs, :] - q_origin[:, None, :]            # (N, B, 3)
        d2 = _dot3(to_v, to_v)
        dist = np.sqrt(np.maximum(d2, 1e-300))
        w = to_v / dist[..., None]
        cos_q = _dot3(w, qn[:, None, :])
        cos_v = -_dot3(w, vpls.normal[None, vs])
        front = (cos_q > 0) & (cos_v > 0)
        qi, vi = np.nonzero(front)
        if len(qi) == 0:
            continue
        occluded = tracer.occluded(q_origin[qi], w[qi, vi].astype(np.float32), 0.0,
                                   (dist[qi, vi] * SHADOW_TMAX_SCALE))
        counters["rays"] += len(qi)
        lit = ~occluded
        qi, vi = qi[lit], vi[lit]
        g = cos_q[qi, vi] * cos_v[qi, vi] / np.maximum(d2[qi, vi], clamp_m * clamp_m)
        contrib = g[:, None] * intensity[vs][vi]
        for c in range(3):
            E[:, c] += np.bincount(qi, weights=contrib[:, c], minlength=n_pts)
    return E, counters


class ProgressiveIrradiance:
    """§3.2: E = (Σ E_i)/n while the scene is unchanged; on a change a new sequence starts with E₀ = E."""

    def __init__(self, n_points: int):
        self.E = np.zeros((n_points, 3), np.float64)
        self._sum = np.zeros((n_points, 3), np.float64)
        self.n = 0
        self.sequences = 1
        self.passes = 0

    def restart(self) -> None:
        """A scene change: the old estimate becomes the first term of the new sequence (E₀ = E)."""
        self.sequences += 1
        if self.n > 0:
            self._sum = self.E.copy()
            self.n = 1

    def add(self, contribution: np.ndarray) -> None:
        self._sum += contribution
        self.n += 1
        self.passes += 1
        self.E = self._sum / self.n
