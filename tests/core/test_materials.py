"""Mirror, glass, glossy and alpha-tested materials: the suite's kernel (suite.core.specular.render_materials)
against Mitsuba on small scenes built so that Mitsuba's integrator computes exactly the light transport the
kernel models.

* Mirror: Mitsuba ``path`` with max_depth 3 = kernel with max_bounces 1. The only diffuse surface is one plane
  (a textured backdrop) lit by a point light: a path from the backdrop would need a fourth vertex to reach the
  backdrop again through the mirror and be lit there, so Mitsuba computes no indirect light; point lights cannot
  be hit by sampled rays, so there are no caustics either.
* Glass: ``path`` with max_depth 4 = max_bounces 2 (in and out of the sphere, then the lit backdrop). Here
  Mitsuba also lights the backdrop by way of the sphere's outer reflection (backdrop -> sphere -> backdrop): the
  backdrop is 6 m behind a 0.6 m sphere, which makes that term < 1e-4 of the backdrop's radiance.
* Glossy: Mitsuba ``direct`` (light + BSDF sampling with MIS) = max_bounces 0, point and area light.
* Alpha: Mitsuba ``volpath`` with max_depth 2, whose shadow rays pass through ``mask`` surfaces with their null
  transmittance and which does not count passing a mask as a bounce (``path`` and ``direct`` do not pass
  shadow rays through masks). The opacity map is binary, so Mitsuba's stochastic mask and the alpha test agree.

Tolerance: the kernel traces one ray through a point and Mitsuba averages a pixel's footprint (box filter), so the
kernel renders at 8 x 8 sub-pixel centres per pixel and averages them (the footprint quadrature error is then
below 1e-4 of the pixel on smooth regions). Pixels whose sub-pixels see different objects, or whose sub-pixel
values spread by more than half their mean (edges, shadow boundaries, refracted edges), or that differ from a
neighbour by more than 30 % (an edge on a pixel border), and their neighbours are excluded. For the rest, per
pixel and channel z = (ours - ref) / sqrt(se_ref^2 + se_ours^2 + (0.002 ref)^2 + (1e-6 mean(ref))^2), with se
from the reference's 16 passes (and, for the area light, the spread of our sub-pixel estimates, an upper bound);
fewer than 0.5 % of values may exceed |z| = 5. The image means must agree within 5 standard errors of their
difference plus 1e-4 of the mean (Mitsuba accumulates samples in float32). Measured agreement is recorded in
docs/core.md. The ``teeth`` tests show that a 10 % error in an IOR or a roughness fails this comparison.
"""
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pytest
from scipy import ndimage

from suite.core.reference import render_with_stderr
from suite.core.scene.builder import SceneBuilder
from suite.core.scene.mitsuba_io import to_mitsuba_dict
from suite.core.scene.model import CameraKey
from suite.core.specular import render_materials
from suite.core.trace import backend_params, make

SUPERSAMPLE = 8
PIXEL_FLOOR = 0.002
BIAS_FLOOR = 1e-4
# Mitsuba leaks about 1e-10 through fully opaque mask texels (float32 opacity a hair below 1): values a million
# times below the image's mean are zero for the comparison.
ABSOLUTE_FLOOR = 1e-6
RES = (48, 36)
ALPHA_RES = (80, 60)  # the grate's bars and holes need a few pixels each
# Every backend; mitsuba-cuda is skipped with its reason where no GPU is usable.
BACKENDS = backend_params("embree", "mitsuba-llvm", "mitsuba-cuda")
CUDA_MARKS = getattr(backend_params("mitsuba-cuda")[0], "marks", ())


# --- scenes ---------------------------------------------------------------------------------------

def checker(tiles=6, a=(0.8, 0.78, 0.72), b=(0.15, 0.3, 0.6), texels=4):
    i = np.arange(tiles * texels) // texels
    parity = (i[:, None] + i[None, :]) % 2
    return np.where(parity[..., None] == 0, np.float32(a), np.float32(b)).astype(np.float32)


def waves(size=64):
    """A smooth colour texture (two slanted waves per channel): refraction and reflection distort it visibly
    without creating edges inside pixels."""
    u = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(u, u, indexing="xy")
    phase = 2 * np.pi * np.stack([3 * uu + vv, uu - 2 * vv, 2 * uu + 3 * vv], axis=-1)
    return (0.45 + 0.3 * np.sin(phase)).astype(np.float32)


def grate_opacity(size=256):
    """A window grate (frame and a cross, 1 = solid). Binary, with texels much smaller than a pixel: at the texel
    corners of a binary map the bilinear 0.5 contour and Mitsuba's stochastic opacity differ (a convex corner
    texel is 15 % opaque under the alpha test, 25 % in expectation under Mitsuba), which fine texels make
    negligible."""
    u = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(u, u, indexing="xy")
    solid = (uu < 0.12) | (uu > 0.88) | (vv < 0.12) | (vv > 0.88) | (np.abs(uu - 0.5) < 0.07) | (np.abs(vv - 0.5) < 0.07)
    return solid.astype(np.float32)


def disc_holes(size=256):
    """Solid except for a round hole in each quadrant."""
    u = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(u, u, indexing="xy")
    du, dv = (uu % 0.5) - 0.25, (vv % 0.5) - 0.25
    return (du * du + dv * dv > 0.15 ** 2).astype(np.float32)


def _backdrop(b, texture="waves"):
    tex = {"waves": waves(), "checker": checker(), None: None}[texture]
    wall = b.add_material("backdrop", albedo=0.5, texture=tex)
    b.add_quad(((0, 0.5, -7), (10, 0, 0), (0, 5, 0)), wall)


def _camera(b, res):
    b.set_camera([CameraKey(0.0, (0, 0.1, 2.6), (0.15, 0, 0))], fov_deg=55, resolution=res)


def mirror_scene(eta=(0.2, 0.9, 1.2), k=(3.9, 2.4, 2.2), res=RES):
    """A backdrop and three mirrors: a tinted conductor facing the camera at an angle, and two seen from the
    back, one two-sided (it reflects) and one one-sided (black, as in Mitsuba)."""
    b = SceneBuilder()
    _backdrop(b, "checker")
    metal = b.add_material("mirror", albedo=0, kind="mirror", specular_reflectance=(0.9, 0.85, 0.8),
                           conductor_eta=eta, conductor_k=k)
    two = b.add_material("two_sided_mirror", albedo=0, kind="mirror", twosided=True)
    one = b.add_material("one_sided_mirror", albedo=0, kind="mirror")
    up = np.array([0.0, 1.0, 0.0])
    n = np.array([-0.97, 0.0, 0.243]) / np.linalg.norm([-0.97, 0.0, 0.243])
    b.add_quad(((1.0, 0.0, -0.8), 0.8 * np.cross(up, n), 0.75 * up), metal)
    back = np.array([-0.97, 0.0, -0.243]) / np.linalg.norm([-0.97, 0.0, -0.243])  # faces away from the camera
    b.add_quad(((-1.0, 0.45, -0.8), 0.45 * np.cross(up, back), 0.35 * up), two)
    b.add_quad(((-1.0, -0.45, -0.8), 0.45 * np.cross(up, back), 0.35 * up), one)
    b.add_point_light("key", (0.5, 2.5, 2.5), 40.0)
    _camera(b, res)
    return b.build("mirror_test")


def glass_scene(ior=1.5, res=RES):
    b = SceneBuilder()
    _backdrop(b)
    glass = b.add_material("glass", albedo=0, kind="glass", int_ior=ior, ext_ior=1.0,
                           specular_transmittance=(1.0, 0.95, 0.9))
    b.add_sphere((-0.3, 0, 0), 0.6, 64, glass)
    b.add_point_light("key", (0.5, 2.5, 2.5), 40.0)
    _camera(b, res)
    return b.build("glass_test")


def glossy_scene(distribution="ggx", conductor_alpha=0.3, plastic_alpha=0.2, res=RES):
    """A floor, a rough gold sphere, a rough plastic sphere and a two-sided rough metal quad seen from the back,
    lit by two point lights and a small area light."""
    other = "beckmann" if distribution == "ggx" else "ggx"
    b = SceneBuilder()
    floor = b.add_material("floor", albedo=(0.45, 0.45, 0.42))
    b.add_quad(((0, -0.6, -2), (0, 0, 4), (4, 0, 0)), floor)
    gold = b.add_material("gold", albedo=0, kind="rough_conductor", roughness=conductor_alpha,
                          distribution=distribution, conductor_eta=(0.143, 0.375, 1.442),
                          conductor_k=(3.983, 2.386, 1.603))
    plastic = b.add_material("plastic", albedo=(0.6, 0.12, 0.08), kind="rough_plastic", roughness=plastic_alpha,
                             distribution=other, int_ior=1.5, ext_ior=1.0, nonlinear=True)
    brushed = b.add_material("brushed", albedo=0, kind="rough_conductor", roughness=conductor_alpha,
                             distribution=distribution, twosided=True, specular_reflectance=(0.8, 0.8, 0.85))
    b.add_sphere((-0.75, 0.0, -1.0), 0.6, 48, gold)
    b.add_sphere((0.75, 0.0, -1.0), 0.6, 48, plastic)
    b.add_quad(((0.0, 0.3, -2.6), (0.0, 0.6, 0.0), (1.2, 0.0, 0.0)), brushed)  # front faces away (-z)
    b.add_point_light("key", (1.5, 2.0, 1.5), 12.0)
    b.add_point_light("rim", (-2.2, 0.4, 0.6), (4.0, 4.5, 5.0))
    b.add_area_light_quad("panel", (-1.2, 1.6, 0.2), (0.6, 0.6), (0.6, -1.0, -0.5), 8.0)
    b.set_camera([CameraKey(0.0, (0, 0.5, 1.8), (0, -0.1, -1.0))], fov_deg=65, resolution=res)
    return b.build("glossy_test")


def alpha_scene(invert=False, threshold=0.5, res=ALPHA_RES):
    """A backdrop behind an alpha-tested diffuse grate lit through it by a point light (its shadow falls on the
    backdrop), and an alpha-tested two-sided rough plastic panel with round holes."""
    b = SceneBuilder()
    _backdrop(b, None)
    mask = grate_opacity()
    grate = b.add_material("grate", albedo=(0.7, 0.5, 0.2), opacity_texture=1.0 - mask if invert else mask,
                           alpha_threshold=threshold)
    glossy = b.add_material("glossy_panel", albedo=(0.2, 0.4, 0.7), kind="rough_plastic", roughness=0.3,
                            distribution="ggx", opacity_texture=disc_holes(), alpha_threshold=threshold,
                            twosided=True)
    b.add_quad(((-0.9, 0.1, -2.0), (0.9, 0, 0), (0, 0.9, 0)), grate)
    b.add_quad(((1.3, 0.2, -1.2), (0.6, 0, 0.25), (0, 0.6, 0)), glossy)
    b.add_point_light("key", (0.6, 0.8, 1.5), 30.0)
    _camera(b, res)
    return b.build("alpha_test")


# --- comparison -----------------------------------------------------------------------------------

@dataclass
class Agreement:
    kept: float  # fraction of pixels compared
    outliers: float  # fraction of compared values with |z| > 5
    bias_z: float  # difference of the means in standard errors
    rel: float  # ours.mean() / ref.mean() - 1 over the compared pixels
    tolerance_z: float  # |bias_z| allowed: 5 plus the float32 floor expressed in standard errors

    @property
    def ok(self) -> bool:
        return self.outliers < 0.005 and abs(self.bias_z) < self.tolerance_z


def render_boxed(scene, backend, **kwargs):
    """Our image box-filtered from SUPERSAMPLE^2 sub-pixel centres, its standard error (from the sub-pixel
    spread; an upper bound) and the pixels to exclude."""
    w, h = scene.camera.resolution
    k = SUPERSAMPLE
    frame = render_materials(scene, make(backend, scene), 0.0, (w * k, h * k), **kwargs)
    sub = frame.image.astype(np.float64).reshape(h, k, w, k, 3)
    image = sub.mean(axis=(1, 3))
    se = sub.std(axis=(1, 3), ddof=1) / k
    g = frame.gbuffer
    # Each pixel's sub-pixels plus the ring of neighbouring sub-pixels around them (a halo of 1/8 pixel), so that
    # an edge lying on a pixel border, which no sub-pixel of the pixel straddles, is still seen.
    def block_range(fine):
        hi = ndimage.maximum_filter(fine, size=3, mode="nearest").reshape(h, k, w, k).max(axis=(1, 3))
        lo = ndimage.minimum_filter(fine, size=3, mode="nearest").reshape(h, k, w, k).min(axis=(1, 3))
        return hi, lo

    obj_hi, obj_lo = block_range(np.where(g.valid, scene.face_object[np.maximum(g.prim, 0)], -1).astype(np.float64))
    plain = frame.image
    if kwargs.get("area_samples", 0) > 0:  # edges from a noise-free render: our area-light noise is no edge
        plain = render_materials(scene, make(backend, scene), 0.0, (w * k, h * k), **{**kwargs, "area_samples": 0}).image
    # A discontinuity (silhouette, shadow or texture edge, refracted edge) is a large step between adjacent
    # sub-pixels; a smooth gradient, however steep, moves little over 1/8 pixel and averages accurately.
    lum = plain.astype(np.float64).mean(axis=-1)
    step = np.zeros_like(lum)
    for axis in (0, 1):
        d = np.abs(np.diff(lum, axis=axis))
        lo_side = [slice(None)] * 2
        hi_side = [slice(None)] * 2
        lo_side[axis], hi_side[axis] = slice(None, -1), slice(1, None)
        step[tuple(lo_side)] = np.maximum(step[tuple(lo_side)], d)
        step[tuple(hi_side)] = np.maximum(step[tuple(hi_side)], d)
    step_hi, _ = block_range(step)
    lum_hi, _ = block_range(lum)
    edge = (obj_hi != obj_lo) | (step_hi > 0.2 * np.maximum(lum_hi, 1e-4))
    return image, se, edge, g


@lru_cache(maxsize=None)
def reference(builder, args, integrator, spp):
    scene = builder(*args)
    ref, se = render_with_stderr(to_mitsuba_dict(scene, 0.0, scene.camera.resolution, integrator=dict(integrator)),
                                 spp=spp, passes=16, seed=7)
    return ref.astype(np.float64), se.astype(np.float64)


def compare(scene, backend, ref, se_ref, stochastic=False, **kwargs):
    """(Agreement, per-pixel material ids, excluded pixels) of our boxed image against the reference."""
    ours, se_ours, edge, g = render_boxed(scene, backend, **kwargs)
    if not stochastic:
        se_ours = np.zeros_like(ours)
    keep = ~edge
    diff = (ours - ref)[keep]
    se2 = (se_ref ** 2 + se_ours ** 2)[keep]
    floored = np.sqrt(se2 + (PIXEL_FLOOR * ref[keep]) ** 2 + (ABSOLUTE_FLOOR * ref.mean()) ** 2)
    z = np.where(floored > 0, diff / np.maximum(floored, 1e-12), np.where(np.abs(diff) < 1e-7, 0.0, np.inf))
    se_mean = np.sqrt(se2.sum())
    bias_z = diff.sum() / se_mean
    tolerance_z = 5.0 + BIAS_FLOOR * abs(ref[keep].sum()) / se_mean
    w, h = scene.camera.resolution
    material = g.material.reshape(h, SUPERSAMPLE, w, SUPERSAMPLE)[:, 0, :, 0]
    return Agreement(float(keep.mean()), float(np.mean(np.abs(z) > 5)), float(bias_z),
                     float(ours[keep].mean() / ref[keep].mean() - 1), float(tolerance_z)), material, edge, ours


def compared_pixels(scene, material, edge, name) -> int:
    return int(((material == [m.name for m in scene.materials].index(name)) & ~edge).sum())


def assert_agrees(a: Agreement, min_kept=0.5):
    assert a.kept > min_kept, f"only {a.kept:.0%} of the pixels were compared"
    assert a.outliers < 0.005, f"{a.outliers:.2%} of the values differ by more than 5 standard errors ({a})"
    assert abs(a.bias_z) < a.tolerance_z, f"image means differ by {a.rel:+.3%} ({a.bias_z:.1f} standard errors; {a})"


MIRROR_REF = (mirror_scene, (), (("type", "path"), ("max_depth", 3)), 1024)
GLASS_REF = (glass_scene, (), (("type", "path"), ("max_depth", 4)), 2048)
ALPHA_REF = (alpha_scene, (), (("type", "volpath"), ("max_depth", 2)), 1024)


def glossy_ref(distribution):
    return (glossy_scene, (distribution,), (("type", "direct"),), 2048)


# --- tests ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("backend", BACKENDS)
def test01_mirrors_match_mitsuba_path(backend):
    ref, se = reference(*MIRROR_REF)
    scene = mirror_scene()
    a, material, edge, ours = compare(scene, backend, ref, se, max_bounces=1)
    assert_agrees(a)
    # The mirrors are part of what is compared: each shows the lit backdrop (or, one-sided from behind, nothing).
    for name, lit in (("mirror", True), ("two_sided_mirror", True), ("one_sided_mirror", False)):
        sel = (material == [m.name for m in scene.materials].index(name)) & ~edge
        assert sel.sum() >= 40, name
        assert (ours[sel].mean() > 0.005) == lit, name
        assert ref[sel].mean() == pytest.approx(ours[sel].mean(), rel=0.01, abs=1e-6), name


@pytest.mark.parametrize("backend", BACKENDS)
def test02_glass_matches_mitsuba_path(backend):
    ref, se = reference(*GLASS_REF)
    scene = glass_scene()
    a, material, edge, _ = compare(scene, backend, ref, se, max_bounces=2)
    assert_agrees(a)
    assert compared_pixels(scene, material, edge, "glass") >= 200  # the refracted image, not only the backdrop


@pytest.mark.parametrize("distribution, backend", [("ggx", "embree"), ("beckmann", "mitsuba-llvm"),
                                                   pytest.param("ggx", "mitsuba-cuda", marks=CUDA_MARKS)])
def test03_glossy_materials_match_mitsuba_direct(distribution, backend):
    ref, se = reference(*glossy_ref(distribution))
    scene = glossy_scene(distribution)
    a, material, edge, _ = compare(scene, backend, ref, se, stochastic=True, max_bounces=0, area_samples=4)
    assert_agrees(a)
    for name in ("gold", "plastic", "brushed"):  # every glossy surface is compared, the back-lit quad included
        assert compared_pixels(scene, material, edge, name) >= 40, name


@pytest.mark.parametrize("backend", BACKENDS)
def test04_alpha_tested_surfaces_match_mitsuba_volpath(backend):
    ref, se = reference(*ALPHA_REF)
    scene = alpha_scene()
    a, material, edge, _ = compare(scene, backend, ref, se, max_bounces=0)
    assert_agrees(a)
    # Both alpha-tested surfaces are among the compared pixels, not only the backdrop seen through them.
    for name in ("grate", "glossy_panel"):
        assert compared_pixels(scene, material, edge, name) >= 250, name


@pytest.mark.parametrize("case", ["glass_ior", "glossy_alpha", "distribution", "conductor_eta", "alpha_mask"])
def test05_teeth_a_wrong_material_parameter_fails_the_comparison(case):
    """The same comparisons with one parameter of ours off by about 10 % (or swapped) fail."""
    if case == "glass_ior":
        (ref, se), scene, kw = reference(*GLASS_REF), glass_scene(ior=1.65), dict(max_bounces=2)
    elif case == "glossy_alpha":
        (ref, se), scene = reference(*glossy_ref("ggx")), glossy_scene("ggx", conductor_alpha=0.33, plastic_alpha=0.22)
        kw = dict(max_bounces=0, area_samples=4)
    elif case == "distribution":
        (ref, se), scene, kw = reference(*glossy_ref("ggx")), glossy_scene("beckmann"), dict(max_bounces=0, area_samples=4)
    elif case == "conductor_eta":
        (ref, se), scene, kw = reference(*MIRROR_REF), mirror_scene(eta=(0.3, 1.0, 1.3)), dict(max_bounces=1)
    else:
        (ref, se), scene, kw = reference(*ALPHA_REF), alpha_scene(threshold=0.999), dict(max_bounces=0)
        scene.materials[1].opacity_texture = 1.0 - scene.materials[1].opacity_texture  # holes where bars were
    a = compare(scene, "embree", ref, se, stochastic="area_samples" in kw, **kw)[0]
    assert not a.ok, f"a wrong {case} went unnoticed: {a}"
