"""The server's compiled passes (methods/layered_pvs/kernels.py) give the bits of their numpy references: depth
peeling with and without the PVS restriction, direct illumination (point and area lights), and whole path-traced
wavefronts (Russian roulette, next-event estimation with the per-point and the power-proportional light choice)
from the same random generator."""
import numpy as np
import pytest

from methods.layered_pvs import server as sv

T_S = 0.5


def _scene(name):
    from suite.core.scene import list_scenes, load
    from suite.core.trace import make

    desc = list_scenes().get(name, "unavailable: not listed")
    if desc.startswith("unavailable"):
        pytest.skip(f"{name}: {desc}")
    scene = load(name)
    tracer = make("embree", scene)
    tracer.update(T_S)
    return scene, tracer


@pytest.fixture(scope="module")
def many_lights():
    """``oa:aggressor`` (109 point lights, 161 emissive triangles), the first two layers at 32x18."""
    scene, tracer = _scene("oa:aggressor@pak1-maps")
    w, h = 32, 18
    view = sv.LayerView(scene.camera.pose_at(T_S), scene.camera.fov_deg, w, h)
    o64, d64 = sv.view_rays(view)
    layers = sv.peel(tracer, o64.astype(np.float32), d64.astype(np.float32), 2, shape=(h, w))
    return scene, tracer, sv.fragments(scene, layers, o64, d64, T_S)


def _same_layers(a, b):
    for name in ("t", "prim", "u", "v"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name


@pytest.mark.parametrize("runs", [False, True])
@pytest.mark.parametrize("restricted", [False, True])
def test01_compiled_peeling_matches_the_numpy_reference(restricted, runs, monkeypatch):
    """Compiled peeling gives the layers of the numpy reference, with its queries whole or traced in runs whose hits
    a worker takes in while the next run is traced."""
    if runs:
        monkeypatch.setattr(sv, "PEEL_SPLIT_MIN", 16)
        calls = []
        start = sv._Handoff.start
        monkeypatch.setattr(sv._Handoff, "start", lambda self, *a: (calls.append(1), start(self, *a))[1])
    scene, tracer = _scene("living_room")
    w, h = 40, 24
    view = sv.LayerView(scene.camera.pose_at(T_S), scene.camera.fov_deg, w, h)
    o64, d64 = sv.view_rays(view)
    o, d = o64.astype(np.float32), d64.astype(np.float32)
    keep = None
    if restricted:  # every third triangle out of the "PVS": many hits are stepped over
        keep = np.ones(scene.num_faces, bool)
        keep[::3] = False
    ref = sv.peel_reference(tracer.intersect, o, d, 6, keep=None if keep is None else (lambda p: keep[p]),
                            shape=(h, w))
    got = sv.peel(tracer, o, d, 6, keep_mask=keep, shape=(h, w))
    _same_layers(ref, got)
    assert ref.valid.sum() > w * h            # more than one layer holds fragments
    if runs:
        assert len(calls) >= 2 * 6            # two runs on the worker per query, every layer
    # a keep callable still works (the reference path)
    if restricted:
        _same_layers(ref, sv.peel(tracer, o, d, 6, keep=lambda p: keep[p], shape=(h, w)))


def test02_direct_illumination_matches_compose_direct(many_lights):
    scene, tracer, frag = many_lights
    assert len(scene.lights_at(T_S)) > 0 and len(scene.emissive_faces()) > 0
    ref = sv.direct_illumination_reference(scene, tracer, frag, T_S, 2, 7)
    got = sv.direct_illumination(scene, tracer, frag, T_S, 2, 7)
    assert got.dtype == ref.dtype and np.array_equal(got, ref)
    assert (ref > 0).any()


@pytest.mark.parametrize("per_point", [True, False])
def test03_compiled_path_tracing_matches_the_numpy_reference(many_lights, monkeypatch, per_point):
    scene, tracer, frag = many_lights
    if not per_point:   # every scene then takes the power-proportional choice (searchsorted on the CDF)
        monkeypatch.setattr(sv.LightSampler, "PER_POINT_LIGHTS", 1)
    # 6 vertices: bounces with and without Russian roulette (from vertex 3 on)
    ref = sv.path_trace_reference(scene, tracer, frag, T_S, 2, 6, 3, np.random.default_rng(3))
    got = sv.path_trace(scene, tracer, frag, T_S, 2, 6, 3, np.random.default_rng(3))
    for r, g in zip(ref, got):
        assert r.dtype == g.dtype and np.array_equal(r, g)


def test04_light_choice_pass_matches_light_sampler():
    """The per-point choice on random points and lights, including lights at the clamp distance."""
    from methods.layered_pvs import kernels

    kernels.jit()
    rng = np.random.default_rng(0)
    ls = sv.LightSampler.__new__(sv.LightSampler)
    ls.centres = rng.random((40, 3)) * 10
    ls.power = rng.random(40) * np.where(rng.random(40) < 0.2, 0.0, 1.0)
    ls.min_d2 = 0.5
    ls.pmf = ls.power / ls.power.sum()
    ls.cdf = np.cumsum(ls.pmf)
    p = np.concatenate([rng.random((500, 3)) * 10, ls.centres[:5]])
    u = np.concatenate([rng.random(len(p) - 2), [0.0, 1.0 - 1e-16]])
    j_ref, pmf_ref = ls.choose(p, u)
    w = np.empty(40)
    for i in range(len(p)):
        j, pmf = kernels._choose_light(p[i, 0], p[i, 1], p[i, 2], u[i], True, ls.power, ls.centres, ls.min_d2,
                                       ls.cdf, ls.pmf, w)
        assert j == j_ref[i] and pmf == pmf_ref[i]


@pytest.mark.parametrize("name", ["gallery", "atrium"])
def test05_peeling_and_path_tracing_equal_their_references(name):
    from suite.core.gbuffer import camera_rays
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load(name)
    tracer = make("embree", scene)
    w, h, t_s = 48, 27, 0.5
    o64, d64 = camera_rays(scene.camera.pose_at(t_s), scene.camera.fov_deg, w, h, dtype=np.float64)
    in_pvs = np.random.default_rng(1).random(scene.num_faces) < 0.7  # a PVS that leaves faces out
    args = (o64.astype(np.float32), d64.astype(np.float32), 3)
    fast = sv.peel(tracer, *args, keep_mask=in_pvs, shape=(h, w))
    ref = sv.peel_reference(tracer.intersect, *args, keep=lambda prim: in_pvs[prim], shape=(h, w))
    for field in ("prim", "t", "u", "v"):
        assert np.array_equal(getattr(fast, field), getattr(ref, field), equal_nan=True), field
    assert (fast.prim[1] >= 0).any() and (fast.prim[0] < 0).any()  # a second layer; holes where the PVS ends
    frag = sv.fragments(scene, fast, o64, d64, t_s)
    out = sv.path_trace(scene, tracer, frag, t_s, 2, 4, 3, np.random.default_rng(7))
    expected = sv.path_trace_reference(scene, tracer, frag, t_s, 2, 4, 3, np.random.default_rng(7))
    for a, b in zip(out, expected):
        assert np.array_equal(a, b)
    assert np.isfinite(out[0]).all() and out[0].max() > 0.0


def test06_client_layer_match_gives_the_choices_of_the_numpy_expressions():
    """Algorithm 4.1's per-point match (kernels._reproject_match) against its statement in numpy: pixel in the
    update's view, nearest layer depth, tolerance test; points behind the eye, outside the view, on pixels with no
    fragment and with a non-finite projection included."""
    from methods.layered_pvs import kernels

    rng = np.random.default_rng(4)
    L, H, W, M = 3, 12, 20, 4000
    depth = np.where(rng.random((L, H, W)) < 0.7, rng.uniform(1, 10, (L, H, W)), np.inf).astype(np.float32)
    depth[:, :2, :3] = np.inf                                   # pixels with no fragment
    eye = np.array([0.5, -0.25, 2.0])
    x_world = eye + rng.normal(size=(M, 3)) * 4
    xy = rng.uniform(-3, W + 3, (M, 2))
    xy[:5] = np.nan
    z = rng.normal(1, 1, M)                                     # some behind the eye
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    prim = rng.integers(0, 50, M)
    tol_rel, pix_angle = 0.01, 0.02
    x_world[6:400] = eye + (x_world[6:400] - eye) / np.linalg.norm(x_world[6:400] - eye, axis=1, keepdims=True) \
        * depth[0, 5, 5].astype(np.float64)                       # points at a layer's distance: matches
    xy[6:400] = (5.5, 5.5)

    out = [np.zeros(M, np.int64) for _ in range(3)] + [np.zeros(M, np.bool_) for _ in range(2)]
    kernels.jit()["_reproject_match"](x_world, xy, z, prim, eye, normals, depth, tol_rel, pix_angle, W, H, *out)
    ix, iy, layer, inside, matched = out

    with np.errstate(invalid="ignore"):
        fx, fy = np.floor(xy[:, 0]), np.floor(xy[:, 1])
        ref_inside = (z > 0) & (fx >= 0) & (fx < W) & (fy >= 0) & (fy < H)
    i = np.flatnonzero(ref_inside)
    ixc, iyc = fx[i].astype(np.int64), fy[i].astype(np.int64)
    to = x_world[i] - eye
    dist = np.linalg.norm(to, axis=1)
    cos = np.abs((to / np.maximum(dist, 1e-30)[:, None] * normals[prim[i]]).sum(1))
    tol = dist * (tol_rel + 1.5 * pix_angle * np.sqrt(np.maximum(1 - cos ** 2, 0)) / np.maximum(cos, 0.05))
    dl = depth[:, iyc, ixc]
    err = np.abs(dl - dist[None, :])
    err[~np.isfinite(dl)] = np.inf
    ref_layer = np.argmin(err, axis=0)
    ref_matched = err[ref_layer, np.arange(len(i))] <= tol

    assert np.array_equal(inside, ref_inside) and not matched[~ref_inside].any()
    assert np.array_equal(ix[i], ixc) and np.array_equal(iy[i], iyc) and np.array_equal(layer[i], ref_layer)
    assert np.array_equal(matched[i], ref_matched)
    assert 300 < ref_matched.sum() < len(i) and (~ref_inside).sum() > 500


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("name", ["oa:aggressor@pak1-maps", "gallery"])
def test07_compiled_fragments_equal_their_reference(name, threads, monkeypatch):
    """The fragments' gathers, facing normals and front-face emission: the bits (signs of zeros included) of the
    numpy reference, on layers that hold back faces and emitters; in one run or split into runs on threads."""
    monkeypatch.setattr(sv, "FRAGMENT_RUN_MIN", 64)
    monkeypatch.setattr(sv.os, "cpu_count", lambda: threads)
    scene, tracer = _scene(name)
    w, h = 64, 36
    view = sv.LayerView(scene.camera.pose_at(T_S), scene.camera.fov_deg, w, h)
    o64, d64 = sv.view_rays(view)
    layers = sv.peel(tracer, o64.astype(np.float32), d64.astype(np.float32), 4, shape=(h, w))
    got, ref = sv.fragments(scene, layers, o64, d64, T_S), sv.fragments_reference(scene, layers, o64, d64, T_S)
    assert all(np.array_equal(a, b) for a, b in zip(got.index, ref.index))
    for field in ("position", "geo_normal", "normal", "albedo", "emission", "view_dir"):
        a, b = getattr(got, field), getattr(ref, field)
        assert a.dtype == b.dtype and np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b)), field
    assert layers.valid[1:].any()


def _svgf_by_the_text(illum, variance, position, normal, valid, depth, pix_angle, iterations, sigma_n,
                      shift_scale=1.0, sigma_l=4.0):
    """SVGF's à-trous passes with §4.4.1's tap choice written out per fragment and tap in plain Python: at each
    5x5 tap (step 2^i) the fragment, among that pixel's layers, closest to the centre fragment's plane shifted
    along its normal by ``shift_scale * depth * pix_angle * tap distance``; weights B3 x B3, normal
    ``max(n.n', 0)^sigma_n``, plane distance ``exp(-|d| / (footprint (tap distance + 1)))`` and luminance
    ``exp(-|l - l'| / (sigma_l sqrt(var)))``; the variance filtered with the squared weights."""
    import math

    h = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)
    lum = lambda c: 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]  # noqa: E731
    L, H, W = valid.shape
    col, var = illum.astype(np.float64), variance.astype(np.float64)
    for i in range(iterations):
        step = 1 << i
        out_c, out_v = col.copy(), var.copy()
        for k in range(L):
            for y in range(H):
                for x in range(W):
                    if not valid[k, y, x]:
                        continue
                    lc, sd, foot = lum(col[k, y, x]), math.sqrt(max(var[k, y, x], 0.0)), depth[k, y, x] * pix_angle
                    n, p = normal[k, y, x], position[k, y, x]
                    wsum = vsum = 0.0
                    c = np.zeros(3)
                    for dy in range(-2, 3):
                        for dx in range(-2, 3):
                            yy, xx = y + dy * step, x + dx * step
                            if not (0 <= yy < H and 0 <= xx < W):
                                continue
                            r = math.sqrt(dx * dx + dy * dy) * step
                            layers = [m for m in range(L) if valid[m, yy, xx]]
                            if not layers:
                                continue
                            dist = {m: float(n @ (position[m, yy, xx] - p)) for m in layers}
                            best = min(layers, key=lambda m: abs(dist[m] - shift_scale * foot * r))
                            ndot = float(n @ normal[best, yy, xx])
                            if ndot <= 0:
                                continue
                            w = (h[dy + 2] * h[dx + 2] * ndot ** sigma_n
                                 * math.exp(-abs(dist[best]) / (foot * (r + 1.0) + 1e-12))
                                 * math.exp(-abs(lc - lum(col[best, yy, xx])) / (sigma_l * sd + 1e-10)))
                            wsum += w
                            vsum += w * w * var[best, yy, xx]
                            c += w * col[best, yy, xx]
                    if wsum > 1e-150:
                        out_c[k, y, x], out_v[k, y, x] = c / wsum, vsum / (wsum * wsum)
        col, var = out_c, out_v
    return col


@pytest.mark.parametrize("sigma_n", [128.0, 3.0, 12.5])
def test08_layered_svgf_follows_the_text(sigma_n):
    """The compiled layered SVGF (``svgf_layers``) against §4.4.1 written out in plain Python, on layers made to
    test the tap choice: two surfaces per pixel a little apart, a third layer in some pixels, slanted and turned
    normals (some facing away), and holes. An integer ``sigma_n`` takes squarings and one exp per tap in the
    kernel, a fractional one the power: equal to rounding (float32 output)."""
    rng = np.random.default_rng(3)
    L, H, W = 3, 9, 11
    valid = np.zeros((L, H, W), bool)
    valid[0] = rng.random((H, W)) < 0.9
    valid[1] = valid[0] & (rng.random((H, W)) < 0.7)
    valid[2] = valid[1] & (rng.random((H, W)) < 0.4)
    depth = np.where(valid, 2.0 + np.arange(L)[:, None, None] * 0.3 + rng.random((L, H, W)) * 0.05, 0.0)
    yy, xx = np.mgrid[0:H, 0:W]
    position = np.stack([xx * 0.02 + 0 * yy, yy * 0.02 + 0 * xx, np.zeros((H, W))], -1)[None] + \
        np.stack([np.zeros_like(depth), np.zeros_like(depth), depth], -1)
    normal = np.zeros((L, H, W, 3))
    normal[..., 2] = -1.0
    normal[..., 0] = rng.normal(0, 0.3, (L, H, W))
    normal[1, ::3, ::2, 2] = 1.0  # some fragments face away from their neighbours
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    illum = np.where(valid[..., None], rng.random((L, H, W, 3)) * 2.0, 0.0)
    variance = np.where(valid, rng.random((L, H, W)) * 0.2, 0.0)
    pix_angle = 2 * np.tan(np.radians(30.0)) / W
    got = sv.svgf_layers(illum, variance, position, normal, valid, depth, pix_angle, iterations=3, sigma_n=sigma_n)
    want = _svgf_by_the_text(illum, variance, position, normal, valid, depth, pix_angle, 3, sigma_n)
    assert got.dtype == np.float32 and got.shape == illum.shape
    assert np.allclose(got[valid], want[valid], rtol=2e-6, atol=1e-7)
    assert not np.allclose(got[valid], illum[valid], rtol=1e-3)  # the filter did filter
    assert (got[~valid] == 0).all()


def test09_the_denoised_fragments_are_svgf_of_their_layer_grids():
    """denoise_fragments scatters its three-channel grids straight into the kernel's layout: its output is
    svgf_layers of the (L, H, W) grids read back at the fragments, bit for bit (holes, a partly filled second layer,
    per-fragment sample variance and the spatial one)."""
    from types import SimpleNamespace

    rng = np.random.default_rng(8)
    L, H, W = 2, 12, 17
    valid = np.zeros((L, H, W), bool)
    valid[0] = rng.random((H, W)) < 0.85
    valid[1] = valid[0] & (rng.random((H, W)) < 0.5)
    index = np.nonzero(valid)
    n = len(index[0])
    t = np.where(valid, 1.5 + rng.random((L, H, W)), np.inf)
    normal = rng.normal(size=(n, 3)) + [0.0, 0.0, -3.0]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    frag = SimpleNamespace(index=index, position=rng.random((n, 3)), normal=normal)
    layers = SimpleNamespace(prim=np.zeros((L, H, W), np.int64), valid=valid, t=t)
    view = SimpleNamespace(fov_deg=60.0, width=W)
    illum, m1 = rng.random((n, 3)), rng.random(n)
    m2 = m1 * m1 + rng.random(n) * 0.1
    got = sv.denoise_fragments(view, layers, frag, illum, m1, m2, spp=2, iterations=3)
    grid = lambda vals, dim: sv.scatter_fragments(vals, index, (L, H, W), dim)  # noqa: E731
    var = sv.spatial_variance(grid(illum, 3), valid, grid(np.maximum(m2 - m1 * m1, 0.0) / 2, 0))
    want = sv.svgf_layers(grid(illum, 3), var, grid(frag.position, 3), grid(normal, 3), valid,
                          np.where(valid, t, 0.0), 2 * np.tan(np.radians(30.0)) / W, iterations=3)[index]
    assert got.dtype == np.float64 and got.shape == (n, 3) and np.array_equal(got, want.astype(np.float64))
    assert not np.allclose(got, illum, rtol=1e-3)
