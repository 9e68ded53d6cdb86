"""Seed 004 §3.1-3.2: the point set Q, VPL shading against a per-pair brute force, progressive accumulation."""
import numpy as np
import pytest

from methods.rail.lighting import (PathVertices, ProgressiveIrradiance, cone_directions, scene_cones,
                                   shade_points)
from methods.rail.pointset import poisson_accept
from suite.core.scene import load
from suite.core.trace import make


def test01_progressive_mean_restarts_with_the_previous_estimate_as_first_term():
    acc = ProgressiveIrradiance(2)
    acc.add(np.full((2, 3), 2.0))
    acc.add(np.full((2, 3), 4.0))
    assert acc.E == pytest.approx(np.full((2, 3), 3.0)) and acc.n == 2       # E = Σ E_i / n
    acc.restart()                                                             # a scene change: E₀ = E
    assert acc.n == 1
    acc.add(np.full((2, 3), 9.0))
    assert acc.E == pytest.approx(np.full((2, 3), 6.0)) and acc.sequences == 2


def test02_vpl_shading_equals_the_per_pair_sum_with_shadow_rays():
    scene = load("living_room")
    tracer = make("embree", scene)
    rng = np.random.default_rng(0)
    lo, hi = (np.asarray(b, float) for b in scene.bounds())
    q = lo + (hi - lo) * rng.uniform(0.2, 0.8, (40, 3))
    qn = rng.normal(size=(40, 3))
    qn /= np.linalg.norm(qn, axis=1, keepdims=True)
    v_pos = lo + (hi - lo) * rng.uniform(0.2, 0.8, (7, 3))
    v_n = rng.normal(size=(7, 3))
    v_n /= np.linalg.norm(v_n, axis=1, keepdims=True)
    vpls = PathVertices(v_pos, v_n, np.full((7, 3), 0.5), rng.uniform(1, 3, (7, 3)), np.ones(7, np.int32),
                        np.zeros(7, np.int32))
    E, counters = shade_points(q, qn, vpls, tracer, clamp_m=0.05, batch=64)
    ref = np.zeros((40, 3))
    for i in range(40):
        for j in range(7):
            d = v_pos[j] - q[i]
            dist = np.linalg.norm(d)
            w = d / dist
            cq, cv = w @ qn[i], -(w @ v_n[j])
            if cq <= 0 or cv <= 0:
                continue
            o = q[i] + 1e-4 * qn[i]
            if tracer.occluded(o[None], w[None].astype(np.float32), 0.0, np.array([dist * 0.999]))[0]:
                continue
            ref[i] += cq * cv / max(dist ** 2, 0.05 ** 2) * vpls.flux[j] * 0.5 / np.pi
    assert counters["pairs"] == 280 and 0 < counters["rays"] <= 280
    np.testing.assert_allclose(E, ref, rtol=1e-4, atol=1e-9)


def test03_distant_lights_emit_only_into_the_cone_that_holds_the_scene():
    axis, cos_max = scene_cones(np.array([[100.0, 0, 0], [0.5, 0, 0]]), np.zeros(3), 2.0)
    assert cos_max[1] == -1.0 and cos_max[0] == pytest.approx(np.sqrt(1 - 0.02 ** 2))
    rng = np.random.default_rng(1)
    d = cone_directions(np.repeat(axis[:1], 5000, 0), np.repeat(cos_max[:1], 5000), rng.random(5000),
                        rng.random(5000))
    o = np.array([100.0, 0, 0])
    t = -(d @ o)                                      # closest approach of each ray to the sphere's centre
    assert (np.linalg.norm(o + t[:, None] * d, axis=1) <= 2.0 + 1e-9).all()


def test04_poisson_disk_darts_keep_their_distance_unless_normals_differ():
    rng = np.random.default_rng(2)
    p = rng.random((3000, 3)) * [5, 5, 0.0]
    n = np.tile([0, 0, 1.0], (3000, 1))
    keep = poisson_accept(p, n, 0.3)
    kept = p[keep]
    d = np.linalg.norm(kept[:, None] - kept[None], axis=-1) + np.eye(len(kept)) * 9
    assert d.min() >= 0.3 and 50 < keep.sum() < 3000
    flipped = np.concatenate([kept, kept])
    nn = np.concatenate([np.tile([0, 0, 1.0], (len(kept), 1)), np.tile([0, 0, -1.0], (len(kept), 1))])
    assert poisson_accept(flipped, nn, 0.3).all()     # two sides of a thin wall both keep their points


def test05_joint_bilateral_upsampling_keeps_surfaces_apart():
    """§3.3: half-resolution irradiance upsampled with bilinear, normal and depth weights does not bleed
    across a depth edge, and reproduces a value that is constant on a surface."""
    from methods.rail.upsample import joint_bilateral_upsample

    h, w, s = 8, 8, 2
    depth = np.where(np.arange(w)[None, :] < 4, 1.0, 10.0) * np.ones((h, 1))
    normal = np.zeros((h, w, 3))
    normal[..., 2] = 1.0
    valid = np.ones((h, w), bool)
    truth = np.where((depth < 5)[..., None], 1.0, 5.0) * np.ones((1, 1, 3))
    sub = (slice(None, None, s), slice(None, None, s))
    up = joint_bilateral_upsample(truth[sub], valid[sub], normal[sub], depth[sub], normal, depth, valid, s)
    np.testing.assert_allclose(up, truth, rtol=1e-3)
