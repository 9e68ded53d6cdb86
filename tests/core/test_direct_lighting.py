"""Our direct lighting agrees with Mitsuba's `direct` integrator on the same scene.

Tolerance, derived from the noise of the images themselves: the reference is rendered in several passes, so
every pixel has a standard error se_ref (suite.core.reference.render_with_stderr); our area-light estimate is
averaged over independent seeds, giving se_ours (point lights are noise-free). For each pixel and channel,
z = (ours - ref) / sqrt(se_ref^2 + se_ours^2 + (0.01 ref)^2). If the two images estimate the same expectation, z
is close to a standard normal variable, so we require
  * fewer than 0.5 % of the compared values with |z| > 5 (a normal variable exceeds 5 with p ~ 6e-7), and
  * the image means to agree within 5 standard errors of their difference (a bias test).
The 1 % relative floor covers the footprint difference on smooth gradients: a box-filtered pixel is its
centre value plus a curvature term (measured up to 0.5 % on the Cornell box walls at 48x48). Excluded: pixels on geometric edges and hard-shadow edges (a 3x3 neighbourhood crossing an object,
normal or shadow boundary), where pixel-centre sampling and Mitsuba's box-filtered pixel legitimately
differ. Mitsuba's `direct` picks one emitter per sample, so with 3 point lights its per-pixel noise is a few
percent even at thousands of spp; the test resolution is small so that this is cheap.
"""
import numpy as np
import pytest
from scipy import ndimage

from suite.core.gbuffer import render_gbuffer
from suite.core.reference import render_with_stderr
from suite.core.scene import load
from suite.core.scene.mitsuba_io import to_mitsuba_dict
from suite.core.shading import direct_lighting, point_light_visibility
from suite.core.trace import backend_params, make


def edge_mask(scene, g, t_s, tracer):
    """Pixels whose 3x3 neighbourhood crosses an object, normal, plane, albedo-texture or hard-shadow boundary."""
    obj = np.where(g.valid, scene.face_object[np.maximum(g.prim, 0)], -1).astype(np.float64)
    keys = [obj, *np.moveaxis(g.normal.astype(np.float64).round(3), -1, 0),
            *np.moveaxis(g.albedo.astype(np.float64).round(3), -1, 0)]
    lights = scene.lights_at(t_s)
    if lights:
        vis = point_light_visibility(g, lights, tracer)
        keys += [vis[..., i].astype(np.float64) for i in range(len(lights))]
    edge = np.zeros(g.valid.shape, bool)
    for k in keys:
        spread = ndimage.maximum_filter(k, size=3, mode="nearest") - ndimage.minimum_filter(k, size=3, mode="nearest")
        edge |= spread > 1e-6
    # Same object and normal but a different plane (a step): distance of neighbours from this pixel's plane.
    p, n = g.position.astype(np.float64), g.normal.astype(np.float64)
    depth = np.where(g.valid, g.depth, 1.0)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            q = np.roll(np.roll(p, dy, 0), dx, 1)
            edge |= np.abs(np.einsum("hwc,hwc->hw", q - p, n)) > 1e-3 * depth
    return edge | ~g.valid


def compare_to_mitsuba_direct(scene_name, resolution, ref_spp, our_samples, seeds, backend):
    scene = load(scene_name)
    t_s = 0.5
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, t_s, resolution)
    runs = np.stack([direct_lighting(scene, g, tracer, t_s, area_samples=our_samples, seed=s) for s in seeds])
    ours = runs.mean(axis=0)
    se_ours = runs.std(axis=0, ddof=1) / np.sqrt(len(seeds)) if len(seeds) > 1 else np.zeros_like(ours)
    ref, se_ref = render_with_stderr(to_mitsuba_dict(scene, t_s, resolution, integrator={"type": "direct"}),
                                     spp=ref_spp, passes=16, seed=7)
    keep = ~edge_mask(scene, g, t_s, tracer)
    diff = (ours - ref)[keep]
    se = np.sqrt(se_ref ** 2 + se_ours ** 2)[keep]
    se_floored = np.sqrt(se ** 2 + (0.01 * ref[keep]) ** 2)
    z = np.where(se_floored > 0, diff / np.maximum(se_floored, 1e-12), np.where(np.abs(diff) < 1e-6, 0.0, np.inf))
    bias_z = diff.sum() / np.sqrt((se ** 2).sum())
    return keep.mean(), np.mean(np.abs(z) > 5), bias_z, ours[keep].mean(), ref[keep].mean()


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test01_area_light_direct_lighting_matches_mitsuba_on_cornell(backend):
    kept, outliers, bias_z, ours_mean, ref_mean = compare_to_mitsuba_direct(
        "cornell", (48, 48), ref_spp=2048, our_samples=64, seeds=tuple(range(8)), backend=backend)
    assert kept > 0.45  # most of the image is compared
    assert outliers < 0.005, f"{outliers:.2%} of pixels differ by more than 5 standard errors"
    assert abs(bias_z) < 5, f"means {ours_mean:.5f} vs {ref_mean:.5f} differ by {bias_z:.1f} standard errors"


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test02_point_light_direct_lighting_matches_mitsuba_on_living_room(backend):
    kept, outliers, bias_z, ours_mean, ref_mean = compare_to_mitsuba_direct(
        "living_room", (64, 36), ref_spp=2048, our_samples=0, seeds=(0,), backend=backend)
    assert kept > 0.45  # most of the image is compared
    assert outliers < 0.005, f"{outliers:.2%} of pixels differ by more than 5 standard errors"
    assert abs(bias_z) < 5, f"means {ours_mean:.5f} vs {ref_mean:.5f} differ by {bias_z:.1f} standard errors"


def test03_a_wrong_light_intensity_is_detected():
    """The comparison has teeth: 5 % too much light fails it."""
    from suite.core.scene.model import PointLight

    scene = load("living_room")
    brighter = [PointLight(lt.name, lt.position, lt.intensity * 1.05) for lt in scene.point_lights]
    resolution, t_s = (64, 36), 0.5
    tracer = make("embree", scene)
    g = render_gbuffer(scene, tracer, t_s, resolution)
    from suite.core.shading import shade_point_lights

    ours = shade_point_lights(g, brighter, point_light_visibility(g, brighter, tracer))
    ref, se_ref = render_with_stderr(to_mitsuba_dict(scene, t_s, resolution, integrator={"type": "direct"}),
                                     spp=2048, passes=16, seed=7)
    keep = ~edge_mask(scene, g, t_s, tracer)
    bias_z = (ours - ref)[keep].sum() / np.sqrt((se_ref[keep] ** 2).sum())
    assert bias_z > 5


def _untextured(name):
    """The scene without albedo textures: the check is about light units and geometry, and texel edges would
    leave no pixel to compare at test resolutions (every texel boundary is an albedo edge)."""
    return _untextured_from(load, name)


def _untextured_from(loader, name):
    import copy
    import dataclasses

    scene = copy.copy(loader(name))
    scene.materials = [dataclasses.replace(m, albedo_texture=None) if m.albedo_texture is not None else m
                       for m in scene.materials]
    return scene


@pytest.mark.parametrize("name,resolution,min_kept", [("dabrovic_sponza", (64, 36), 0.05),
                                                       ("oa:aggressor@pak1-maps", (96, 54), 0.10)])
def test04_direct_lighting_matches_mitsuba_on_the_real_scenes(name, resolution, min_kept):
    """Sponza's sidecar lights and a Quake III map's converted light entities, sun / sky lights and surface-light
    triangles: our direct lighting and Mitsuba's agree (the units of the converters are right)."""
    from suite.core.scene import list_scenes

    desc = list_scenes().get(name, "unavailable: not listed")
    if desc.startswith("unavailable"):
        pytest.skip(desc)
    kept, outliers, bias_z, ours_mean, ref_mean = _compare_untextured(name, resolution)
    assert kept > min_kept
    assert outliers < 0.005, f"{outliers:.2%} of pixels differ by more than 5 standard errors"
    assert abs(bias_z) < 5, f"means {ours_mean:.5f} vs {ref_mean:.5f} differ by {bias_z:.1f} standard errors"


def _compare_untextured(name, resolution):
    # compare_to_mitsuba_direct loads by name through this module's `load`
    global load
    real = load
    load = lambda spec: _untextured_from(real, spec)  # noqa: E731
    try:
        return compare_to_mitsuba_direct(name, resolution, ref_spp=1024, our_samples=16, seeds=tuple(range(4)),
                                         backend="embree")
    finally:
        load = real
