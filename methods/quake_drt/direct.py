"""Direct illumination stage (seed 001 §4.1, §6.6, Algorithm 6.2) with light culling and light subsampling.

For every shading point (a diffuse or glossy surface that the primary or secondary stage reached) the stage
reads its row of the light visibility table (:mod:`.culling`; the all-lights row when ``rt_cullLights`` is off)
and shoots shadow rays:

* ``k = 0`` (the thesis's ``rt_numRandomDL 0``) or ``k >= n``: one ray to each of the n candidate lights,
  weight 1 (Algorithm 6.2 without subsampling; "k larger than the culled light count" uses them all);
* ``k < n``, ``mode = "uniform"``: k *distinct* lights chosen uniformly (Floyd's algorithm), weight n / k.
  Each light is chosen with probability k / n, so the estimator is unbiased (tests/methods/quake_drt/
  test_estimator.py proves it against the all-lights image within its standard error);
* ``k < n``, ``mode = "power"``: k independent choices with probability proportional to emitted power
  (``LightList.power``) among the n candidates, weight 1 / (k p_l): unbiased too, fewer samples wasted on
  weak lights. On maps with sun and sky lights (point lights 10 km away, with enormous flux but ordinary
  irradiance) nearly every sample goes to them and the other lights' share of the image converges only after
  millions of frames: measured on kaos, 64 frames of it hold 5 % of the image's light;
* ``k < n``, ``mode = "irradiance"``: the same with probabilities proportional to each light's intensity over its
  squared distance to the row's clusters (:func:`row_irradiance_cdf`): the suite's improvement for such maps.

Two defects of the public implementation of the thesis (``lights.glsl`` of Quake-III-Arena-R) are avoided: the
random index ``int(round(u * n))`` can be n, one past the row (an out-of-range light index, and the end lights
get half the probability); here the index is ``floor(u * n)`` with 24-bit ``u < 1``, so always ``< n``. And
``amplification = totalNumLights / numLights`` divides two unsigned integers, so 5 lights subsampled to 2 weigh
2 instead of 2.5 (a downward bias); here the weight is a float. Light indices are int32 throughout (the table
is a CSR list, not a bit mask), so any number of lights works.

A point light at distance d adds ``w * f * cos_x * I / d^2``; an area light sampled at a point y adds
``w * f * cos_x * cos_y * L_e * A / d^2`` (soft shadows: a uniform random point; ``rt_softshadows 0``: the
light's representative point). Distances are clamped at ``min_distance`` so a light exactly on a surface stays
finite; a light below the surface's geometric horizon or behind a one-sided emitter gets no ray. For Lambertian
surfaces f = 1/pi and the stage returns *illumination* (radiance / albedo), which is what the denoiser filters;
for glossy ones it returns radiance (their albedo for demodulation is 1).

Compiled kernels do the per-ray work. ``_generate`` picks the lights of each point (the subsampling above) and
writes their shadow rays straight into the tracer's frame (origins offset as
``suite.core.trace.robust.offset_ray_origin`` does), in one pass without per-sample intermediate arrays (its
two-pass reference is ``_select`` then ``_rays``); ``_accumulate`` adds the unoccluded rays to their points (the
sums of ``np.bincount``). Rays go in chunks of at most ``chunk_rays``, growing from a short first chunk (so that
the backend starts tracing at once); a worker thread adds up the previous chunk and generates the next one while
the backend traces the current one, so the stage costs little more than its occlusion queries (the ``rays`` part
of ``splitbench bench quake_drt``).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np

from methods.quake_drt.rng import DIM_LIGHTS
from suite.core.shading import SHADOW_TMAX_SCALE
from suite.core.trace.robust import FLOAT_SCALE, OFFSET_ULPS

MODES = ("uniform", "power", "irradiance")
INV_PI = 1.0 / np.pi
DEFAULT_CHUNK_RAYS = 1 << 20
# Light samples of the first chunk and the largest chunk of the pipelined loop of :func:`shade` (the first is
# generated while the backend waits; later ones while it traces the previous chunk).
PIPELINE_FIRST_SAMPLES = 1 << 13
PIPELINE_MAX_SAMPLES = 1 << 18


# The numba twin of rng.pcg_np / rng.uniform_np (same bits; tests/methods/quake_drt/test_rng.py).
_MASK = 0xFFFFFFFF
_INV_2_24 = 1.0 / 16777216.0


@numba.njit(inline="always")
def pcg_nb(v):
    # numba widens uint32 arithmetic to 64 bits; masking after each product keeps numpy's uint32 wrap-around.
    m = np.uint64(_MASK)
    state = (np.uint64(v) * np.uint64(747796405) + np.uint64(2891336453)) & m
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state) * np.uint64(277803737)) & m
    return (word >> np.uint64(22)) ^ word


@numba.njit(inline="always")
def uniform_nb(seed, dim):
    m = np.uint64(_MASK)
    h = pcg_nb((np.uint64(seed) & m) ^ pcg_nb((np.uint64(dim) + np.uint64(0x9E3779B9)) & m))
    return np.float64(h >> np.uint64(8)) * _INV_2_24


@numba.njit(cache=True, nogil=True)
def jitter_nb(seeds, first, end, dim_x, dim_y, jx, jy):
    """The anti-aliasing jitter of pixels ``first:end`` (``uniform - 0.5`` in x and y, the primary stage's
    :func:`.primary.camera_rays`), in one pass (the hash stays in this file: numba's cache watches the kernel's own
    file only)."""
    for k in range(first, end):
        jx[k] = uniform_nb(seeds[k], dim_x) - 0.5
        jy[k] = uniform_nb(seeds[k], dim_y) - 0.5



@dataclass
class ShadingPoints:
    """Surfaces to light: where primary rays and specular chains ended on diffuse or glossy materials."""

    pixel: np.ndarray  # (N,) int64 row-major pixel index
    throughput: np.ndarray  # (N, 3) float64 product of specular weights along the chain (1 for primary hits)
    p: np.ndarray  # (N, 3) float64 world position
    ng: np.ndarray  # (N, 3) float64 geometric normal on the side the ray arrived from
    ns: np.ndarray  # (N, 3) float64 shading normal the BSDF is evaluated around
    wi: np.ndarray  # (N, 3) float64 unit direction toward the viewer
    albedo: np.ndarray  # (N, 3) float64
    material: np.ndarray  # (N,) int64
    prim: np.ndarray  # (N,) int64 face id
    seed: np.ndarray  # (N,) uint32 random stream (the pixel's seed, or one derived per chain)
    lambert: np.ndarray  # (N,) bool: diffuse kinds (f = albedo / pi); False = glossy (full BSDF)

    def __len__(self) -> int:
        return int(len(self.pixel))

    @staticmethod
    def concat(parts: list) -> "ShadingPoints":
        """The parts' points in order; a single part with points is returned as it is (no copy of its fields: shading
        points are not written to once made)."""
        parts = [p for p in parts if p is not None and len(p)]
        if not parts:
            return ShadingPoints.empty()
        if len(parts) == 1:
            return parts[0]
        return ShadingPoints(*[np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS])

    @staticmethod
    def empty() -> "ShadingPoints":
        z3 = np.zeros((0, 3))
        return ShadingPoints(np.zeros(0, np.int64), z3, z3, z3, z3, z3, z3, np.zeros(0, np.int64),
                             np.zeros(0, np.int64), np.zeros(0, np.uint32), np.zeros(0, bool))

    def subset(self, sel) -> "ShadingPoints":
        return ShadingPoints(*[getattr(self, f)[sel] for f in _FIELDS])


_FIELDS = ("pixel", "throughput", "p", "ng", "ns", "wi", "albedo", "material", "prim", "seed", "lambert")


@dataclass
class DirectStats:
    candidates: int = 0  # sum over points of the lights in their row (after culling)
    selected: int = 0  # sum over points of the lights chosen (after subsampling)
    rays: int = 0  # shadow rays traced (selected minus those below the horizon / behind the emitter)
    visible: int = 0  # unoccluded shadow rays


@numba.njit(cache=True, nogil=True)
def _find(cdf, a, n, u):
    """First index j in [0, n) with cdf[a + j] > u (binary search), clamped to n - 1."""
    lo, hi = 0, n - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[a + mid] > u:
            hi = mid
        else:
            lo = mid + 1
    return lo


@numba.njit(inline="always")
def _choose(i, a, n, k, mode, row_lights, row_cdf, seeds, chosen, l_light, l_weight, l_dim):
    """The light samples (light, weight, random dimension) of point i, whose table row holds the n lights
    ``row_lights[a:a + n]``, written to ``l_*``: the subsampling of :func:`_select` for one point (the same
    operations in the same order). Returns their count."""
    take = n if (k == 0 or k >= n) else k
    count = 0
    if take == n:
        # Every candidate (thesis Alg. 6.2), weight 1. The light's own index picks its random numbers, so
        # culled and unculled frames sample each light identically.
        for j in range(n):
            light = row_lights[a + j]
            l_light[count], l_weight[count], l_dim[count] = light, 1.0, DIM_LIGHTS + 4 * light
            count += 1
    elif mode == 0:
        # k distinct lights, uniformly (Floyd's algorithm); each is in the sample with probability k / n.
        m = 0
        for j in range(n - k, n):
            t = int(uniform_nb(seeds[i], DIM_LIGHTS + 4 * m) * (j + 1))
            if t > j:
                t = j
            dup = False
            for q in range(m):
                if chosen[q] == t:
                    dup = True
                    break
            chosen[m] = j if dup else t
            m += 1
        weight = n / k  # float division: 5 lights subsampled to 2 weigh 2.5
        for q in range(k):
            l_light[count], l_weight[count], l_dim[count] = row_lights[a + chosen[q]], weight, DIM_LIGHTS + 4 * q
            count += 1
    else:
        # k independent choices from the row's distribution (power or irradiance, ``row_cdf``).
        for q in range(k):
            j = _find(row_cdf, a, n, uniform_nb(seeds[i], DIM_LIGHTS + 4 * q))
            pj = row_cdf[a + j] - (row_cdf[a + j - 1] if j > 0 else 0.0)
            if pj <= 0.0:
                continue
            l_light[count], l_weight[count], l_dim[count] = row_lights[a + j], 1.0 / (k * pj), DIM_LIGHTS + 4 * q
            count += 1
    return count


@numba.njit(cache=True, nogil=True)
def _select(i0, rows, row_off, row_lights, row_cdf, k, mode, seeds, chosen, s_point, s_light, s_weight, s_dim):
    """Light subsampling: the (point, light, weight, random dimension) samples of points i0, i0 + 1, ... until
    the sample arrays are full. Returns (samples, next point, candidates, selected). With :func:`_rays`: the two-pass reference of
    :func:`_generate`."""
    cap = s_point.shape[0]
    count = 0
    cand = 0
    sel = 0
    n_pts = rows.shape[0]
    i = i0
    while i < n_pts:
        r = rows[i]
        a = row_off[r]
        n = row_off[r + 1] - a
        take = n if (k == 0 or k >= n) else k
        if count + take > cap:
            if i == i0:
                raise ValueError("chunk_rays is smaller than one point's light count")
            break
        cand += n
        sel += take
        if take == n:
            # Every candidate (thesis Alg. 6.2), weight 1. The light's own index picks its random numbers, so
            # culled and unculled frames sample each light identically.
            for j in range(n):
                light = row_lights[a + j]
                s_point[count], s_light[count], s_weight[count] = i, light, 1.0
                s_dim[count] = DIM_LIGHTS + 4 * light
                count += 1
        elif mode == 0:
            # k distinct lights, uniformly (Floyd's algorithm); each is in the sample with probability k / n.
            m = 0
            for j in range(n - k, n):
                t = int(uniform_nb(seeds[i], DIM_LIGHTS + 4 * m) * (j + 1))
                if t > j:
                    t = j
                dup = False
                for q in range(m):
                    if chosen[q] == t:
                        dup = True
                        break
                chosen[m] = j if dup else t
                m += 1
            weight = n / k  # float division: 5 lights subsampled to 2 weigh 2.5
            for q in range(k):
                s_point[count], s_light[count], s_weight[count] = i, row_lights[a + chosen[q]], weight
                s_dim[count] = DIM_LIGHTS + 4 * q
                count += 1
        else:
            # k independent choices from the row's distribution (power or irradiance, ``row_cdf``).
            for q in range(k):
                j = _find(row_cdf, a, n, uniform_nb(seeds[i], DIM_LIGHTS + 4 * q))
                pj = row_cdf[a + j] - (row_cdf[a + j - 1] if j > 0 else 0.0)
                if pj <= 0.0:
                    continue
                s_point[count], s_light[count], s_weight[count] = i, row_lights[a + j], 1.0 / (k * pj)
                s_dim[count] = DIM_LIGHTS + 4 * q
                count += 1
        i += 1
    return count, i, cand, sel


@numba.njit(cache=True, nogil=True)
def _rays(n_samples, s_point, s_light, s_weight, s_dim, origin, ng, ns, lambert, seeds, kind, lpos, lrgb, larea,
          tri_off, tri_p0, tri_e1, tri_e2, tri_n, tri_cdf, rep_tri, soft, shift, min_d2, tmax_scale, o_out, d_out,
          len_out, w_out, ray_point, ray_light):
    """The shadow ray of every sample, in the tracer's frame, compacted to the samples whose light is above the
    point's horizon and faces it. Returns the ray count."""
    count = 0
    for q in range(n_samples):
        i = s_point[q]
        light = s_light[q]
        dimbase = s_dim[q]
        ox, oy, oz = origin[i, 0], origin[i, 1], origin[i, 2]
        if kind[light] == 0:
            yx, yy, yz = lpos[light, 0], lpos[light, 1], lpos[light, 2]
            nyx, nyy, nyz = 0.0, 0.0, 0.0
        else:
            a = tri_off[light]
            if soft:
                t = a + _find(tri_cdf, a, tri_off[light + 1] - a, uniform_nb(seeds[i], dimbase + 1))
                su = np.sqrt(uniform_nb(seeds[i], dimbase + 2))
                b1 = 1.0 - su
                b2 = uniform_nb(seeds[i], dimbase + 3) * su
            else:
                t = rep_tri[light]
                b1 = 1.0 / 3.0
                b2 = 1.0 / 3.0
            yx = tri_p0[t, 0] + b1 * tri_e1[t, 0] + b2 * tri_e2[t, 0]
            yy = tri_p0[t, 1] + b1 * tri_e1[t, 1] + b2 * tri_e2[t, 1]
            yz = tri_p0[t, 2] + b1 * tri_e1[t, 2] + b2 * tri_e2[t, 2]
            nyx, nyy, nyz = tri_n[t, 0], tri_n[t, 1], tri_n[t, 2]
        tx, ty, tz = yx - ox, yy - oy, yz - oz
        d2 = tx * tx + ty * ty + tz * tz
        dist = np.sqrt(d2)
        inv = 1.0 / max(dist, 1e-30)
        dx, dy, dz = tx * inv, ty * inv, tz * inv
        if dx * ng[i, 0] + dy * ng[i, 1] + dz * ng[i, 2] <= 0.0:
            continue  # below the geometric horizon: the surface shadows itself
        cos_x = dx * ns[i, 0] + dy * ns[i, 1] + dz * ns[i, 2]
        if lambert[i] and cos_x <= 0.0:
            continue
        g = s_weight[q] / max(d2, min_d2)
        if kind[light] != 0:
            cos_y = -(dx * nyx + dy * nyy + dz * nyz)
            if cos_y <= 0.0:
                continue  # behind the one-sided emitter
            g *= cos_y * larea[light]
        if lambert[i]:
            g *= cos_x * 0.3183098861837907
        o_out[count, 0] = ox - shift[0]
        o_out[count, 1] = oy - shift[1]
        o_out[count, 2] = oz - shift[2]
        d_out[count, 0], d_out[count, 1], d_out[count, 2] = dx, dy, dz
        len_out[count] = max(np.float32(dist * tmax_scale), np.float32(0.0))
        w_out[count, 0] = g * lrgb[light, 0]
        w_out[count, 1] = g * lrgb[light, 1]
        w_out[count, 2] = g * lrgb[light, 2]
        ray_point[count] = i
        ray_light[count] = light
        count += 1
    return count


@numba.njit(cache=True, nogil=True)
def _generate(i0, cap, rows, row_off, row_lights, row_cdf, k, mode, chosen, l_light, l_weight, l_dim, p, ng, ns,
              lambert, seeds, kind, lpos, lrgb, larea, tri_off, tri_p0, tri_e1, tri_e2, tri_n, tri_cdf, rep_tri, soft,
              shift, min_d2, tmax_scale, o_out, d_out, len_out, w_out, ray_point):
    """:func:`_select` and :func:`_rays` in one pass, with the robust origin of each point
    (:func:`suite.core.trace.robust.offset_ray_origin` along ``ng``, its float64 operations in their order)
    computed when the point is reached: the shadow rays of points i0, i0 + 1, ... whose light samples (at most
    ``cap`` of them, before the horizon tests) fit, written straight to the output rows, with no per-sample
    intermediate arrays. Returns (rays, next point, candidates, selected); the rays and their order are those of
    the two-pass reference."""
    count = 0
    samples = 0
    cand = 0
    sel = 0
    n_pts = rows.shape[0]
    i = i0
    while i < n_pts:
        r = rows[i]
        a = row_off[r]
        n = row_off[r + 1] - a
        take = n if (k == 0 or k >= n) else k
        if samples + take > cap:
            if i == i0:
                raise ValueError("chunk_rays is smaller than one point's light count")
            break
        cand += n
        sel += take
        samples += take
        m = _choose(i, a, n, k, mode, row_lights, row_cdf, seeds, chosen, l_light, l_weight, l_dim)
        # offset_ray_origin: OFFSET_ULPS float32 ULPs of the largest tracing-frame coordinate, at least FLOAT_SCALE.
        mag = np.float32(max(max(abs(p[i, 0] - shift[0]), abs(p[i, 1] - shift[1])), abs(p[i, 2] - shift[2])))
        step = max(OFFSET_ULPS * np.float64(np.spacing(mag)), FLOAT_SCALE)
        ox, oy, oz = p[i, 0] + step * ng[i, 0], p[i, 1] + step * ng[i, 1], p[i, 2] + step * ng[i, 2]
        for q in range(m):
            # The body of _rays (kept verbatim, so that the two give the same bits). One shared helper inlined by
            # numba (inline="always", the ray returned as a tuple) gave the same bits but made the direct stage
            # 1.38x slower (oa:aggressor 320x180, 2 cores: 780 against 564 ms).
            light = l_light[q]
            dimbase = l_dim[q]
            if kind[light] == 0:
                yx, yy, yz = lpos[light, 0], lpos[light, 1], lpos[light, 2]
                nyx, nyy, nyz = 0.0, 0.0, 0.0
            else:
                a = tri_off[light]
                if soft:
                    t = a + _find(tri_cdf, a, tri_off[light + 1] - a, uniform_nb(seeds[i], dimbase + 1))
                    su = np.sqrt(uniform_nb(seeds[i], dimbase + 2))
                    b1 = 1.0 - su
                    b2 = uniform_nb(seeds[i], dimbase + 3) * su
                else:
                    t = rep_tri[light]
                    b1 = 1.0 / 3.0
                    b2 = 1.0 / 3.0
                yx = tri_p0[t, 0] + b1 * tri_e1[t, 0] + b2 * tri_e2[t, 0]
                yy = tri_p0[t, 1] + b1 * tri_e1[t, 1] + b2 * tri_e2[t, 1]
                yz = tri_p0[t, 2] + b1 * tri_e1[t, 2] + b2 * tri_e2[t, 2]
                nyx, nyy, nyz = tri_n[t, 0], tri_n[t, 1], tri_n[t, 2]
            tx, ty, tz = yx - ox, yy - oy, yz - oz
            d2 = tx * tx + ty * ty + tz * tz
            dist = np.sqrt(d2)
            inv = 1.0 / max(dist, 1e-30)
            dx, dy, dz = tx * inv, ty * inv, tz * inv
            if dx * ng[i, 0] + dy * ng[i, 1] + dz * ng[i, 2] <= 0.0:
                continue  # below the geometric horizon: the surface shadows itself
            cos_x = dx * ns[i, 0] + dy * ns[i, 1] + dz * ns[i, 2]
            if lambert[i] and cos_x <= 0.0:
                continue
            g = l_weight[q] / max(d2, min_d2)
            if kind[light] != 0:
                cos_y = -(dx * nyx + dy * nyy + dz * nyz)
                if cos_y <= 0.0:
                    continue  # behind the one-sided emitter
                g *= cos_y * larea[light]
            if lambert[i]:
                g *= cos_x * 0.3183098861837907
            o_out[count, 0] = ox - shift[0]
            o_out[count, 1] = oy - shift[1]
            o_out[count, 2] = oz - shift[2]
            d_out[count, 0], d_out[count, 1], d_out[count, 2] = dx, dy, dz
            len_out[count] = max(np.float32(dist * tmax_scale), np.float32(0.0))
            w_out[count, 0] = g * lrgb[light, 0]
            w_out[count, 1] = g * lrgb[light, 1]
            w_out[count, 2] = g * lrgb[light, 2]
            ray_point[count] = i
            count += 1
        i += 1
    return count, i, cand, sel


@numba.njit(cache=True, nogil=True)
def _accumulate(count, occluded, w, ray_point, out):
    """``out[point] += w`` for every unoccluded ray, in ray order: the sums of ``np.bincount(point, weights)``
    (which adds in the same order) without compacting the lit rays first. Returns the unoccluded count."""
    visible = 0
    for r in range(count):
        if occluded[r]:
            continue
        i = ray_point[r]
        out[i, 0] += w[r, 0]
        out[i, 1] += w[r, 1]
        out[i, 2] += w[r, 2]
        visible += 1
    return visible


def row_cdf(row_offsets: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(S,) cumulative normalised ``weights`` (one per entry of the rows' light lists) within each row."""
    w = np.maximum(np.asarray(weights, np.float64), 0.0)
    counts = np.diff(row_offsets)
    cs = np.concatenate([[0.0], np.cumsum(w)])
    owner = np.repeat(np.arange(len(counts)), counts)
    start = cs[row_offsets[owner]]
    total = cs[row_offsets[owner + 1]] - start
    cdf = np.where(total > 0, (cs[1:] - start) / np.where(total > 0, total, 1.0), 0.0)
    ends = row_offsets[1:][counts > 0] - 1
    cdf[ends[cdf[ends] > 0]] = 1.0  # exact ends: a uniform number below 1 always finds a light
    return cdf


def row_power_cdf(row_offsets: np.ndarray, row_lights: np.ndarray, power: np.ndarray) -> np.ndarray:
    """(S,) the ``power`` mode's distribution: each row's lights in proportion to their emitted flux."""
    return row_cdf(row_offsets, np.asarray(power, np.float64)[row_lights])


def row_irradiance_cdf(table, lights) -> np.ndarray:
    """(S,) the ``irradiance`` mode's distribution: each row's lights in proportion to the irradiance they could
    give the row's clusters, intensity (I, or L_e x A for an area light) over the squared distance from the light to
    the centre of the clusters' bounds, the distance at least their half-diagonal. Unlike flux, this does not let a
    sun 10 km away (huge flux, ordinary irradiance) take every sample."""
    from methods.quake_drt.lights import POINT

    counts = np.diff(table.row_offsets)
    owner = np.repeat(np.arange(len(counts)), counts)
    li = np.asarray(table.row_lights, np.int64)
    if table.row_centre is None:
        return row_power_cdf(table.row_offsets, table.row_lights, lights.power)
    d2 = ((lights.position[li] - table.row_centre[owner]) ** 2).sum(axis=1)
    d2 = np.maximum(d2, table.row_radius[owner] ** 2 + 1e-12)
    intensity = lights.rgb.mean(axis=1) * np.where(lights.kind == POINT, 1.0, lights.area)
    return row_cdf(table.row_offsets, intensity[li] / d2)


def trace_shadow(tracer, o_local, d, length, skip_faces=None):
    """Occlusion of rays in the tracer's frame. ``skip_faces`` (bool per face): surfaces that do not cast shadows
    (the primary stage's transparent overlays); a ray the backend finds blocked is then re-resolved by a
    closest-hit walk that passes them."""
    soa = bool(getattr(tracer, "soa_origins", False))
    if hasattr(tracer, "occluded_local"):
        occ = tracer.occluded_local(np.ascontiguousarray(o_local.T) if soa else o_local, d, length)
    else:
        shift = getattr(tracer, "shift", np.zeros(3))
        occ = tracer.occluded(o_local.astype(np.float64) + shift, d, 0.0, length)
    occ = np.asarray(occ, bool)
    if skip_faces is not None and occ.any():
        from methods.quake_drt.primary import walk_past

        idx = np.nonzero(occ)[0]
        shift = getattr(tracer, "shift", np.zeros(3))
        o_world = o_local[idx].astype(np.float64) + shift
        hits = walk_past(tracer, o_world, d[idx].astype(np.float64), length[idx].astype(np.float64), skip_faces)
        occ = occ.copy()
        occ[idx] = hits.prim >= 0
    return occ


def shade(points: ShadingPoints, lights, table, rows: np.ndarray, k: int, mode: str, soft: bool, tracer, scene,
          min_distance: float, chunk_rays: int = DEFAULT_CHUNK_RAYS, skip_faces=None,
          row_cdf: np.ndarray | None = None, capture: list | None = None,
          on_device: bool = True) -> tuple[np.ndarray, DirectStats]:
    """(N, 3) illumination of every shading point (radiance / albedo for Lambertian points, radiance for glossy
    ones) and the work done. ``rows`` are the table rows the points read (:func:`.culling.point_rows`).
    ``capture``: a list that receives the shadow rays the stage traces, for the benchmark's raw replay: on the host
    path a copy of every chunk ``(o, d, length)`` in the tracer's frame, on the device path ``("o", Ray3f)`` per
    iteration of the device loop.

    On a Dr.Jit backend (a tracer with a ``device``; ``on_device`` False forces the host path) the Lambertian points
    are shaded by the device kernel of :mod:`methods.quake_drt.device_direct` (the same bits on ``llvm_ad_rgb``) and
    glossy ones, whose BSDF has no device kernel, by the host path."""
    n = len(points)
    stats = DirectStats()
    if n == 0 or len(lights) == 0:
        return np.zeros((n, 3), np.float64), stats
    if mode not in MODES:
        raise ValueError(f"unknown light sampling mode '{mode}'")
    if row_cdf is None:
        if mode == "power":
            row_cdf = row_power_cdf(table.row_offsets, table.row_lights, lights.power)
        elif mode == "irradiance":
            row_cdf = row_irradiance_cdf(table, lights)
        else:
            row_cdf = np.zeros(len(table.row_lights))
    rows = np.ascontiguousarray(rows, np.int64)
    dev = getattr(tracer, "device", None) if on_device else None
    if dev is None:
        return _shade_host(points, lights, table, rows, k, mode, soft, tracer, scene, min_distance, chunk_rays,
                           skip_faces, row_cdf, capture)
    return _shade_device(dev, points, lights, table, rows, k, mode, soft, tracer, scene, min_distance, chunk_rays,
                         skip_faces, row_cdf, capture)


def _shade_device(dev, points, lights, table, rows, k, mode, soft, tracer, scene, min_distance, chunk_rays, skip_faces,
                  row_cdf, capture):
    """:func:`shade` on ``dev``: Lambertian points there, glossy ones on the host path (module docstring)."""
    from methods.quake_drt import device_direct

    out = np.zeros((len(points), 3), np.float64)
    counts = np.diff(np.asarray(table.row_offsets, np.int64))[rows]
    stats = DirectStats(candidates=int(counts.sum()), selected=int((counts if k == 0 else np.minimum(counts, k)).sum()))
    lam = np.asarray(points.lambert, bool)
    if lam.any():
        # all Lambertian (the usual case): the points as they are (a copy of every field costs more than the kernel)
        sel, sub = (slice(None), points) if lam.all() else (np.nonzero(lam)[0], points.subset(lam))
        args = (dev, sub, lights, table, rows[sel], int(k), mode, bool(soft), float(min_distance), skip_faces, row_cdf)
        if capture is not None:
            device_direct.shade(*args, record=capture)
        il, rays, visible, extra = device_direct.shade(*args)
        out[sel] = il
        stats.rays += rays
        stats.visible += visible
        tracer.counters["rays_occluded"] += rays
        tracer.counters["rays_intersect"] += extra
    if not lam.all():
        sel = np.nonzero(~lam)[0]
        il, st = _shade_host(points.subset(sel), lights, table, rows[sel], k, mode, soft, tracer, scene, min_distance,
                             chunk_rays, skip_faces, row_cdf, capture)
        out[sel] = il
        stats.rays += st.rays
        stats.visible += st.visible
    return out, stats


def _shade_host(points, lights, table, rows, k, mode, soft, tracer, scene, min_distance, chunk_rays, skip_faces,
                row_cdf, capture):
    """:func:`shade` on the host: compiled ray generation pipelined with the backend's occlusion queries."""
    n = len(points)
    out = np.zeros((n, 3), np.float64)
    stats = DirectStats()
    mode_code = MODES.index(mode)
    counts = np.diff(table.row_offsets)[rows]
    per_point = counts if k == 0 else np.minimum(counts, k)
    widest = int(per_point.max(initial=1))
    total = int(per_point.sum())
    cap = int(max(1, min(total, max(int(chunk_rays), widest))))
    # Chunks grow from PIPELINE_FIRST_SAMPLES to PIPELINE_MAX_SAMPLES (never above chunk_rays, never below one
    # point's samples): the backend starts tracing after a short first chunk, and later chunks are large enough
    # that the per-chunk call overhead vanishes. A point's samples never straddle two chunks, so its sum is
    # the same whatever the chunking.
    top = min(cap, max(PIPELINE_MAX_SAMPLES, widest))
    chunk_caps = [min(top, max(PIPELINE_FIRST_SAMPLES << j, widest)) for j in range(32)]
    shift = np.asarray(getattr(tracer, "shift", np.zeros(3)), np.float64)
    seeds = np.ascontiguousarray(points.seed, np.uint32)
    selection = (rows, table.row_offsets, table.row_lights, row_cdf, int(k), mode_code)
    geometry = (np.ascontiguousarray(points.p, np.float64), np.ascontiguousarray(points.ng, np.float64),
                np.ascontiguousarray(points.ns, np.float64), np.ascontiguousarray(points.lambert, np.bool_), seeds,
                lights.kind, lights.position, lights.rgb, lights.area, lights.tri_offsets,
                np.ascontiguousarray(lights.tri_p0), lights.tri_e1, lights.tri_e2, lights.tri_normal, lights.tri_cdf,
                lights.rep_tri, bool(soft), shift, float(min_distance) ** 2, float(SHADOW_TMAX_SCALE))
    glossy = not bool(np.all(points.lambert))
    slots = [_Buffers(top, max(int(k), widest)) for _ in range(2 if total > chunk_caps[0] else 1)]

    def accumulate(slot):
        """Adds the unoccluded rays of the chunk ``slot`` holds (traced, not yet added) to ``out``."""
        count, occ = traced[slot]
        traced[slot] = None
        b = slots[slot]
        if not glossy:
            return int(_accumulate(count, occ, b.w, b.ray_point, out))
        lit = np.nonzero(~occ)[0]
        pt = b.ray_point[lit]
        w = _apply_glossy_bsdf(scene, points, pt, b.d[lit].astype(np.float64), b.w[lit])
        for c in range(3):
            out[:, c] += np.bincount(pt, weights=w[:, c], minlength=n)
        return int(len(lit))

    def produce(i, slot, chunk):
        # The chunk this slot held is added first (its buffers are about to be overwritten).
        visible = accumulate(slot) if traced[slot] is not None else 0
        b = slots[slot]
        return visible, *_generate(i, chunk_caps[min(chunk, len(chunk_caps) - 1)], *selection, b.chosen, b.l_light,
                                   b.l_weight, b.l_dim, *geometry, b.o, b.d, b.length, b.w, b.ray_point)

    # A worker adds up the previous chunk and generates the next one's rays (compiled, GIL released) while the
    # backend traces the current one's; the two buffer slots alternate. A point's rays all lie in one chunk and
    # its sum starts from zero, so the order in which chunks are added does not change a bit. (Glossy points
    # are added on the caller's thread: their BSDF is numpy.)
    traced = [None] * len(slots)  # per slot: (rays, occluded) of a traced chunk not yet added
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(produce, 0, 0, 0)
        slot, chunk = 0, 0
        while True:
            visible, count, i_next, cand, sel = pending.result()
            stats.visible += visible
            chunk += 1
            if i_next < n:
                other = 1 - slot
                if glossy and traced[other] is not None:
                    stats.visible += accumulate(other)
                pending = pool.submit(produce, i_next, other, chunk)
            stats.candidates += int(cand)
            stats.selected += int(sel)
            if count:
                b = slots[slot]
                o, d, length = b.o[:count], b.d[:count], b.length[:count]
                if capture is not None:
                    capture.append((o.copy(), d.copy(), length.copy()))
                traced[slot] = (count, trace_shadow(tracer, o, d, length, skip_faces))
                stats.rays += int(count)
            if i_next >= n:
                break
            slot = 1 - slot if len(slots) > 1 else 0
    for held in range(len(slots)):  # the last chunks
        if traced[held] is not None:
            stats.visible += accumulate(held)
    return out, stats


class _Buffers:
    """One slot of ray buffers: the light samples of one point and a chunk's rays."""

    def __init__(self, cap: int, widest: int):
        self.chosen = np.empty(max(widest, 1), np.int64)
        self.l_light, self.l_weight = np.empty(max(widest, 1), np.int64), np.empty(max(widest, 1), np.float64)
        self.l_dim = np.empty(max(widest, 1), np.int64)
        self.o, self.d = np.empty((cap, 3), np.float32), np.empty((cap, 3), np.float32)
        self.length, self.w = np.empty(cap, np.float32), np.empty((cap, 3), np.float64)
        self.ray_point = np.empty(cap, np.int32)


def _apply_glossy_bsdf(scene, points: ShadingPoints, pt: np.ndarray, wo: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Multiplies the rays of glossy points by their BSDF times cos (Mitsuba's ``eval``; suite.core.bsdf)."""
    from suite.core.bsdf import eval_bsdf

    glossy = ~points.lambert[pt]
    if not glossy.any():
        return w
    w = w.copy()
    idx = np.nonzero(glossy)[0]
    mats = points.material[pt[idx]]
    for mid in np.unique(mats):
        sel = idx[mats == mid]
        p = pt[sel]
        w[sel] *= eval_bsdf(scene.materials[int(mid)], points.wi[p], wo[sel], points.ns[p], points.albedo[p])
    return w
