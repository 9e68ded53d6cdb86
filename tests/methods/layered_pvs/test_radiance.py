"""The server's first layer has the brightness of Mitsuba's ``path`` integrator on a many-light map.

Scene: ``oa:aggressor@pak1-maps`` (109 point lights: light entities, sun and sky lights; 161 emissive triangles),
without albedo textures as in tests/core/test_direct_lighting.py (texel edges are a pixel-footprint question,
not a light-transport one), 48x27, the camera pose at 0.5 s, paths of up to 5 vertices on both sides.

Tolerance, from the noise: our first layer is rendered with ``SEEDS`` independent random streams, giving the
standard error se_ours of its image mean; the reference is rendered in passes, giving se_ref per pixel (their
mean's error is the root sum of squares over the pixels). A mean per channel agrees when
|ours - ref| < 5 sqrt(se_ours^2 + se_ref^2) + 1 % of ref; the 1 % covers pixel-centre sampling against
Mitsuba's box-filtered pixel (as in the direct-lighting test).

The denoised layer (what the server packs) may lose some energy: the à-trous filter's luminance edge-stopping
leaves rare bright path samples out of their neighbours' averages. The allowance for that is 15 % (measured
4-11 % on this map at 0.25-2 s). Choosing one light per primary fragment among the ~100 made those rare bright
samples the bulk of the direct light, and the denoised layer came out at about half the reference.
"""
import copy
import dataclasses

import numpy as np
import pytest

from methods.layered_pvs import server as sv

SCENE = "oa:aggressor@pak1-maps"
RES = (48, 27)
T_S = 0.5
SPP, MAX_DEPTH, RR_DEPTH, ITERATIONS = 4, 5, 3, 5
SEEDS = 4
DENOISE_ALLOWANCE = 0.15


@pytest.fixture(scope="module")
def first_layer():
    from suite.core.reference import render_with_stderr
    from suite.core.scene import list_scenes, load
    from suite.core.scene.mitsuba_io import to_mitsuba_dict
    from suite.core.trace import make

    desc = list_scenes().get(SCENE, "unavailable: not listed")
    if desc.startswith("unavailable"):
        pytest.skip(f"{SCENE}: {desc}")
    scene = copy.copy(load(SCENE))
    scene.materials = [dataclasses.replace(m, albedo_texture=None) if m.albedo_texture is not None else m
                       for m in scene.materials]
    tracer = make("embree", scene)
    tracer.update(T_S)
    w, h = RES
    view = sv.LayerView(scene.camera.pose_at(T_S), scene.camera.fov_deg, w, h)
    o64, d64 = sv.view_rays(view)
    layers = sv.peel(tracer, o64.astype(np.float32), d64.astype(np.float32), 1, shape=(h, w))
    frag = sv.fragments(scene, layers, o64, d64, T_S)
    raw, denoised = [], []
    for seed in range(SEEDS):
        illum, m1, m2 = sv.path_trace(scene, tracer, frag, T_S, SPP, MAX_DEPTH, RR_DEPTH,
                                      np.random.default_rng(seed))
        den = sv.denoise_fragments(view, layers, frag, illum, m1, m2, SPP, ITERATIONS)
        raw.append((illum * frag.albedo + frag.emission).sum(axis=0) / (w * h))
        denoised.append((den * frag.albedo + frag.emission).sum(axis=0) / (w * h))
    ref, se_ref = render_with_stderr(
        to_mitsuba_dict(scene, T_S, RES, integrator={"type": "path", "max_depth": MAX_DEPTH}),
        spp=256, passes=8, seed=3)
    ref_mean = ref.reshape(-1, 3).astype(np.float64).mean(axis=0)
    ref_se = np.sqrt((se_ref.reshape(-1, 3).astype(np.float64) ** 2).sum(axis=0)) / (w * h)
    return np.array(raw), np.array(denoised), ref_mean, ref_se


def test01_path_traced_first_layer_mean_radiance_matches_mitsuba_path_within_noise(first_layer):
    raw, _, ref_mean, ref_se = first_layer
    ours = raw.mean(axis=0)
    se_ours = raw.std(axis=0, ddof=1) / np.sqrt(len(raw))
    tol = 5 * np.sqrt(se_ours ** 2 + ref_se ** 2) + 0.01 * ref_mean
    assert np.all(np.abs(ours - ref_mean) < tol), f"ours {ours} vs Mitsuba {ref_mean} (tolerance {tol})"


def test02_denoised_first_layer_keeps_the_reference_brightness(first_layer):
    _, denoised, ref_mean, ref_se = first_layer
    ours = denoised.mean(axis=0)
    se_ours = denoised.std(axis=0, ddof=1) / np.sqrt(len(denoised))
    noise = 5 * np.sqrt(se_ours ** 2 + ref_se ** 2)
    assert np.all(ours > (1 - DENOISE_ALLOWANCE) * ref_mean - noise), f"denoised {ours} vs Mitsuba {ref_mean}"
    assert np.all(ours < ref_mean + noise + 0.01 * ref_mean), f"denoised {ours} vs Mitsuba {ref_mean}"
