"""Secondary rays (seed 001 §6.5): with every effect off and all branches traced, the renderer's mirrors, glass
and glossy surfaces match the suite's material kernel (suite.core.specular.render_materials), and one random
branch per glass interface is an unbiased estimate of tracing both."""
import numpy as np
import pytest

from suite.core.scene.builder import SceneBuilder
from suite.core.scene.model import CameraKey
from suite.core.specular import render_materials

RES = (64, 48)


@pytest.fixture
def materials_scene():
    b = SceneBuilder()
    wall = b.add_material("wall", albedo=(0.7, 0.6, 0.5))
    floor = b.add_material("floor", albedo=(0.3, 0.5, 0.6))
    mirror = b.add_material("mirror", albedo=0.0, kind="mirror", specular_reflectance=(0.9, 0.9, 0.8))
    glass = b.add_material("glass", albedo=0.0, kind="glass", int_ior=1.5)
    metal = b.add_material("metal", albedo=0.0, kind="rough_conductor", roughness=0.2, conductor_eta=(0.2, 0.4, 1.4),
                           conductor_k=(3.9, 2.4, 1.8), twosided=True)
    b.add_box((-4, 0, -4), (4, 3, 4), wall, inward=True, open_faces=("-y",))
    b.add_quad(((0, 0.0, 0), (0, 0, 4.0), (4.0, 0, 0)), floor)
    b.add_quad(((1.5, 1.2, -2.5), (1.0, 0, 0.6), (0, 0.9, 0)), mirror)
    b.add_sphere((-1.0, 0.8, -1.0), 0.7, 24, glass)
    b.add_sphere((0.9, 0.5, 0.2), 0.45, 20, metal)
    b.add_point_light("key", (0.5, 2.6, 1.5), intensity=(9.0, 8.5, 8.0))
    b.add_point_light("fill", (-3.0, 2.0, 2.5), intensity=(3.0, 3.0, 4.0))
    b.set_camera([CameraKey(0.0, (0.0, 1.5, 3.6), (0.0, 0.8, -1.0))], fov_deg=70.0, resolution=RES)
    return b.build("materials")


def test01_all_branches_without_effects_match_the_material_kernel(renderer, materials_scene):
    scene = materials_scene
    r = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene", max_depth=5)
    img, raw = r.raw(1)
    assert raw.info["secondary_rays"] > 0
    ref = render_materials(scene, r.tracer, 0.0, RES, max_bounces=5).image
    rel = np.abs(img - ref).max(axis=-1) / np.maximum(ref.max(axis=-1), 1e-3)
    assert (rel < 1e-3).mean() > 0.995, f"{(rel >= 1e-3).mean():.4f} of pixels differ"
    assert abs(img.mean() - ref.mean()) / ref.mean() < 1e-3


def test02_one_random_branch_is_unbiased(renderer, materials_scene):
    scene = materials_scene
    both, _ = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene").raw(1)
    r = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene", all_branches=False)
    stack = r.raw_stack(96)
    glass = np.std(stack, axis=0).max(axis=-1) > 0
    assert glass.mean() > 0.02  # the glass sphere's pixels are noisy
    n = len(stack)
    blocks = stack.reshape(n, RES[1] // 4, 4, RES[0] // 4, 4, 3).mean(axis=(2, 4))
    ref = both.reshape(RES[1] // 4, 4, RES[0] // 4, 4, 3).mean(axis=(1, 3))
    se = blocks.std(axis=0, ddof=1) / np.sqrt(n)
    noisy = se > 1e-6
    z = (blocks.mean(axis=0) - ref)[noisy] / se[noisy]
    assert (np.abs(z) > 4.5).mean() < 0.01
    assert np.allclose(blocks.mean(axis=0)[~noisy], ref[~noisy], rtol=1e-4, atol=1e-6)


def test03_glossy_reflections_blur_the_mirror_and_keep_other_pixels(renderer, materials_scene):
    scene = materials_scene
    sharp, raw = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene").raw(1)
    glossy = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene", glossy_reflections=True,
                      glossy_cone_deg=10.0).raw_stack(8).mean(axis=0)
    mirror = raw.g.kind == 1
    assert mirror.sum() > 20
    assert not np.allclose(glossy[mirror], sharp[mirror], rtol=1e-3)
    untouched = ~mirror & (raw.g.kind == 0)
    assert np.allclose(glossy[untouched], sharp[untouched], rtol=1e-5, atol=1e-7)


def _secondary_inputs(renderer, scene, **settings):
    from methods.quake_drt import primary

    r = renderer(scene, None, RES, num_random_dl=0, pvs="none", transparency="scene", antialiasing=True, **settings)
    seeds = r.seeds(3)
    _, surf = primary.primary_stage(scene, r.tracer, 0.0, None, RES, seeds, True)
    return r, seeds, surf


def _same_result(a, b):
    fields = ("pixel", "throughput", "p", "ng", "ns", "wi", "albedo", "material", "prim", "seed", "lambert")
    return (a.rays_per_depth == b.rays_per_depth and np.array_equal(a.emission, b.emission)
            and all(np.array_equal(getattr(a.points, f), getattr(b.points, f)) for f in fields)
            and all(np.array_equal(getattr(a, f), getattr(b, f))
                    for f in ("guide_pixel", "guide_p", "guide_n", "guide_depth")))


@pytest.mark.parametrize("all_branches", [True, False])
@pytest.mark.parametrize("min_chains", [1, 10 ** 9], ids=["two threads", "one part"])
def test04_the_compiled_passes_have_the_bits_of_the_numpy_reference(renderer, materials_scene, monkeypatch,
                                                                    all_branches, min_chains):
    """Mirror (Fresnel conductor), glass (both branches, or one picked at random), the two-sided rough conductor's
    BSDF normal and the guides: every ray, weight, point and guide of the compiled stage equals the reference's,
    whether its parts run on two threads or there is one part."""
    from methods.quake_drt import secondary

    monkeypatch.setattr(secondary, "PART_MIN_CHAINS", min_chains)
    r, seeds, surf = _secondary_inputs(renderer, materials_scene)
    ref = secondary.secondary_stage_reference(materials_scene, r.tracer, 0.0, surf, seeds, 5, all_branches)
    out = secondary.secondary_stage(materials_scene, r.tracer, 0.0, surf, seeds, 5, all_branches)
    assert sum(ref.rays_per_depth) > 100 and len(ref.points) > 50 and len(ref.rays_per_depth) >= 3
    assert (ref.points.lambert == 0).any() and ref.points.lambert.any()  # glossy metal and diffuse walls reached
    assert _same_result(out, ref)
    # One guide per pixel with a shading point (the stage's pixel count reads it).
    assert np.array_equal(np.sort(out.guide_pixel), np.unique(out.points.pixel))


def test05_the_frame_does_not_depend_on_how_the_chains_are_split(renderer, materials_scene, monkeypatch):
    """A pixel's chains stay in one part and keep their order, so its emission and shading sums are the same."""
    from methods.quake_drt import secondary

    images = []
    for parts, min_chains in ((1, 1), (2, 1), (3, 1)):
        monkeypatch.setattr(secondary, "PARTS", parts)
        monkeypatch.setattr(secondary, "PART_MIN_CHAINS", min_chains)
        images.append(renderer(materials_scene, None, RES, num_random_dl=0, pvs="none", transparency="scene",
                               max_depth=5).raw(2)[0])
    assert np.array_equal(images[0], images[1]) and np.array_equal(images[0], images[2])


def test06_parts_split_the_chains_by_work():
    """Contiguous runs covering every chain, of about equal weight (two rays per depth for a chain that takes
    both branches of glass, one for a mirror's), not of equal chain counts."""
    from methods.quake_drt.secondary import part_bounds

    weight = np.r_[np.full(300, 2.0), np.ones(600)]
    b = part_bounds(weight, 2)
    assert b[0] == 0 and b[-1] == 900 and np.all(np.diff(b) >= 0)
    assert [weight[x:y].sum() for x, y in zip(b[:-1], b[1:])] == [600.0, 600.0]  # 300 glass | 600 mirror chains
    assert list(part_bounds(np.ones(10), 3)) == [0, 4, 7, 10] and list(part_bounds(np.ones(7), 1)) == [0, 7]
    assert list(part_bounds(np.ones(0), 2)) == [0, 0]


def test07_the_guide_is_the_first_of_the_strongest_chains_as_lexsort_picks_it():
    """Ties keep the first point, NaN strengths lose to numbers: the pick of ``np.lexsort((-strength, pixel))``."""
    from methods.quake_drt import secondary

    rng = np.random.default_rng(4)
    pixel = rng.integers(0, 40, 400)
    thr = rng.integers(0, 3, (400, 3)).astype(np.float64)  # many equal sums
    thr[rng.random(400) < 0.05, 1] = np.nan
    best = secondary._strongest(pixel, thr, 50)
    strength = thr.sum(axis=1)
    order = np.lexsort((-strength, pixel))
    first = order[np.r_[True, np.diff(pixel[order]) != 0]]
    assert np.array_equal(best[best >= 0], first)
    assert (best[np.setdiff1d(np.arange(50), pixel)] == -1).all()
