"""References: Mitsuba renders in passes with a standard error, and the content-addressed EXR cache.

Images are tiny (16x16 and below) and sample counts low; the noise test states its statistical tolerance.
"""
import os

import numpy as np
import pytest

from suite.core import reference
from suite.errors import UserError
from suite.core.reference import (cached_render, direct_reference, path_reference, reference_path_for,
                             render_mitsuba_dict, render_with_stderr, scene_reference)
from suite.core.scene.model import CameraKey, CameraPath, Material, PointLight, Scene

VARIANT = "llvm"


@pytest.fixture
def mi():
    from suite.core.env import mitsuba

    return mitsuba(VARIANT)


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))


def cornell_dict(mi, size=16):
    scene_dict = mi.cornell_box()
    scene_dict["sensor"]["film"]["width"] = size
    scene_dict["sensor"]["film"]["height"] = size
    return scene_dict


def tiny_scene(block_albedo=(0.8, 0.2, 0.2), texture=None, light_position=(0.0, 2.0, 0.5)):
    """A floor and a floating block lit by one point light, seen from above at 16x12 pixels."""
    positions = [[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1],
                 [-0.3, 0.5, -0.3], [0.3, 0.5, -0.3], [0.3, 0.5, 0.3], [-0.3, 0.5, 0.3]]
    faces = [[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]]
    uvs = [[0, 0], [1, 0], [1, 1], [0, 1]] * 2
    materials = [Material("floor", (0.5, 0.5, 0.5), albedo_texture=texture), Material("block", block_albedo)]
    camera = CameraPath([CameraKey(0.0, (0.0, 3.0, 3.0), (0.0, 0.0, 0.0)),
                         CameraKey(1.0, (1.0, 3.0, 3.0), (0.0, 0.0, 0.0))], fov_deg=50.0, resolution=(16, 12))
    return Scene(name="tiny", positions=positions, normals=[[0, 1, 0]] * 8, uvs=uvs, faces=faces,
                 face_material=[0, 0, 1, 1], face_object=[0, 0, 1, 1], object_names=["floor", "block"],
                 materials=materials, point_lights=[PointLight("key", light_position, (4.0, 4.0, 4.0))],
                 camera=camera)


def cache_files(directory):
    return sorted(os.listdir(directory)) if os.path.isdir(directory) else []


# --- rendering ----------------------------------------------------------------------------------------

def test01_cornell_reference_is_finite_non_negative_contiguous_rgb(mi):
    img = render_mitsuba_dict(cornell_dict(mi), spp=16, seed=0, variant=VARIANT)
    assert img.shape == (16, 16, 3) and img.dtype == np.float32 and img.flags.c_contiguous
    assert np.isfinite(img).all() and (img >= 0).all()
    assert img.mean() > 0.01  # the box is lit, not black


def test02_film_is_forced_to_rgb_hdrfilm(mi):
    scene_dict = cornell_dict(mi, size=12)
    scene_dict["sensor"]["film"]["pixel_format"] = "rgba"
    assert render_mitsuba_dict(scene_dict, spp=2, variant=VARIANT).shape == (12, 12, 3)
    scene_dict["sensor"]["film"] = {"type": "specfilm", "width": 12, "height": 12}
    with pytest.raises(UserError, match="hdrfilm"):
        render_mitsuba_dict(scene_dict, spp=2, variant=VARIANT)


def test03_same_seed_reproduces_and_another_seed_differs(mi):
    # With a box filter every sample lands in its own pixel, so the render is bit-reproducible; splatting
    # filters (Mitsuba's default Gaussian) add across threads in varying order and differ in the last bit.
    scene_dict = cornell_dict(mi, size=12)
    scene_dict["sensor"]["film"]["rfilter"] = {"type": "box"}
    first = render_mitsuba_dict(scene_dict, spp=8, seed=1, variant=VARIANT)
    np.testing.assert_array_equal(render_mitsuba_dict(scene_dict, spp=8, seed=1, variant=VARIANT), first)
    assert not np.array_equal(render_mitsuba_dict(scene_dict, spp=8, seed=2, variant=VARIANT), first)


def test04_stderr_shrinks_as_one_over_sqrt_spp(mi):
    scene_dict = cornell_dict(mi)
    _, stderr_low = render_with_stderr(scene_dict, spp=64, passes=8, seed=0, variant=VARIANT)
    _, stderr_high = render_with_stderr(scene_dict, spp=1024, passes=8, seed=1, variant=VARIANT)
    # 16x more samples -> 4x smaller error. The median over pixel channels is used because a few pixels next
    # to the light dominate a mean. Over ten other seed pairs this ratio ranged from 3.56 to 4.17; ±15 % of 4
    # is allowed.
    lit = (stderr_low > 0) & (stderr_high > 0)
    ratio = float(np.median(stderr_low[lit]) / np.median(stderr_high[lit]))
    assert 3.4 < ratio < 4.6, ratio


def test05_stderr_predicts_the_spread_between_independent_renders(mi):
    scene_dict = cornell_dict(mi, size=12)
    means, stderrs = zip(*(render_with_stderr(scene_dict, spp=64, passes=8, seed=s, variant=VARIANT)
                           for s in range(10, 20)))
    observed = np.std(np.stack(means), axis=0, ddof=1)
    predicted = np.sqrt(np.mean(np.square(np.stack(stderrs)), axis=0))
    lit = predicted > 0
    # The spread of 10 renders is itself uncertain by about ±8 % in this pixel average (0.92 to 1.04 for
    # three other seed sets); agreement within 20 % is required.
    assert float(observed[lit].mean() / predicted[lit].mean()) == pytest.approx(1.0, abs=0.2)


def test06_single_pass_has_unknown_stderr(mi):
    mean, stderr = render_with_stderr(cornell_dict(mi, size=12), spp=4, passes=1, variant=VARIANT)
    assert np.isfinite(mean).all() and np.isinf(stderr).all()


@pytest.mark.parametrize("spp, passes", [(0, None), (4, 5), (4, 0)])
def test07_impossible_sample_counts_are_user_errors(mi, spp, passes):
    with pytest.raises(UserError, match="spp|passes"):
        render_with_stderr(cornell_dict(mi, size=12), spp=spp, passes=passes, variant=VARIANT)


def test08_scene_dict_without_sensor_is_a_user_error(mi):
    scene_dict = {k: v for k, v in cornell_dict(mi).items() if k != "sensor"}
    with pytest.raises(UserError, match="sensor"):
        render_mitsuba_dict(scene_dict, spp=2, variant=VARIANT)


def test09_default_passes_bound_samples_per_pass():
    assert reference.default_passes(256, (16, 16)) == reference.DEFAULT_PASSES
    assert reference.default_passes(4, (16, 16)) == 4
    passes = reference.default_passes(4096, (1920, 1080))
    assert 1920 * 1080 * 4096 / passes <= reference.MAX_SAMPLES_PER_PASS + 1920 * 1080


# --- cache ----------------------------------------------------------------------------------------

def test10_cache_hit_returns_identical_images_without_rendering(mi, monkeypatch):
    scene_dict = cornell_dict(mi, size=12)
    first = cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=8, passes=4, variant=VARIANT)
    assert not first.from_cache
    files_before = {p: (first.path.parent / p).read_bytes() for p in cache_files(first.path.parent)}

    def must_not_render(*args, **kwargs):
        raise AssertionError("a cached reference was rendered again")

    monkeypatch.setattr(reference, "render_with_stderr", must_not_render)
    second = cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=8, passes=4, variant=VARIANT)
    assert second.from_cache and second.path == first.path and second.key == first.key
    np.testing.assert_array_equal(second.image, first.image)
    np.testing.assert_array_equal(second.stderr, first.stderr)
    assert {p: (first.path.parent / p).read_bytes() for p in cache_files(first.path.parent)} == files_before
    assert sorted(files_before) == sorted(f"{first.key}{ext}" for ext in (".exr", ".stderr.exr", ".json"))


def test11_failed_cache_write_leaves_no_entry(mi, monkeypatch):
    scene_dict = cornell_dict(mi, size=12)
    real_write_exr = reference.write_exr
    calls = []

    def fail_on_mean(path, img):
        calls.append(path)
        if str(path).endswith(".stderr.exr"):
            return real_write_exr(path, img)
        raise OSError("disk full")

    monkeypatch.setattr(reference, "write_exr", fail_on_mean)
    with pytest.raises(OSError, match="disk full"):
        cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=4, passes=2, variant=VARIANT)
    assert len(calls) == 2
    assert cache_files(reference.cache_dir()) == []
    monkeypatch.setattr(reference, "write_exr", real_write_exr)
    assert not cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=4, passes=2,
                             variant=VARIANT).from_cache


def test12_cache_lives_under_splitbench_cache_or_the_working_directory(tmp_path, monkeypatch):
    assert reference.cache_dir() == tmp_path / "cache" / "references"
    monkeypatch.delenv("SPLITBENCH_CACHE")
    monkeypatch.chdir(tmp_path / "..")
    assert reference.cache_dir() == (tmp_path / "..").resolve() / "cache" / "references"


def test13_unreadable_cache_entry_is_a_user_error_naming_it(mi):
    scene_dict = cornell_dict(mi, size=12)
    ref = cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=4, passes=2, variant=VARIANT)
    ref.path.write_bytes(b"damaged")
    with pytest.raises(UserError, match=ref.key):
        cached_render({"scene": "cornell-12"}, lambda: scene_dict, spp=4, passes=2, variant=VARIANT)


# --- keys of scene references ------------------------------------------------------------------------

BASE = dict(t_s=0.0, resolution=(16, 12), spp=16, integrator=None, seed=0, variant=VARIANT, passes=None)
CHANGES = {
    "spp": dict(spp=32),
    "seed": dict(seed=1),
    "t_s": dict(t_s=0.5),
    "resolution": dict(resolution=(12, 16)),
    "passes": dict(passes=4),
    "max_depth": dict(integrator={"type": "path", "max_depth": 3}),
    "integrator": dict(integrator={"type": "direct"}),
}
SCENE_CHANGES = {
    "albedo": dict(block_albedo=(0.8, 0.2, 0.25)),
    "texture": dict(texture=np.full((2, 2, 3), 0.5, np.float32)),
    "light": dict(light_position=(0.0, 2.0, 0.6)),
}


def test14_equal_scenes_share_a_key():
    assert reference_path_for(tiny_scene(), **BASE) == reference_path_for(tiny_scene(), **BASE)


@pytest.mark.parametrize("change", sorted(CHANGES))
def test15_render_settings_change_the_key(change):
    assert reference_path_for(tiny_scene(), **{**BASE, **CHANGES[change]}) != reference_path_for(tiny_scene(), **BASE)


@pytest.mark.parametrize("change", sorted(SCENE_CHANGES))
def test16_scene_content_changes_the_key(change):
    assert reference_path_for(tiny_scene(**SCENE_CHANGES[change]), **BASE) != reference_path_for(tiny_scene(), **BASE)


def test17_texel_change_changes_the_key():
    texture = np.full((2, 2, 3), 0.5, np.float32)
    changed = texture.copy()
    changed[1, 1, 2] = 0.51
    assert (reference_path_for(tiny_scene(texture=texture), **BASE)
            != reference_path_for(tiny_scene(texture=changed), **BASE))


# --- scene references end to end ---------------------------------------------------------------------

def test18_path_reference_of_a_scene_renders_once_then_reads_the_cache(monkeypatch):
    scene = tiny_scene()
    first = scene_reference(scene, t_s=0.0, resolution=(16, 12), spp=16, variant=VARIANT)
    assert first.image.shape == (12, 16, 3) and first.stderr.shape == (12, 16, 3)
    assert np.isfinite(first.image).all() and (first.image >= 0).all() and first.image.max() > 0
    assert first.path == reference_path_for(scene, **BASE)
    monkeypatch.setattr(reference, "render_with_stderr", None)  # any render attempt would fail
    image, stderr = path_reference(scene, 0.0, (16, 12), spp=16, variant=VARIANT, return_stderr=True)
    np.testing.assert_array_equal(image, first.image)
    np.testing.assert_array_equal(stderr, first.stderr)


def test19_direct_reference_is_stored_apart_from_the_path_reference():
    scene = tiny_scene()
    direct = direct_reference(scene, 0.0, (16, 12), spp=16, variant=VARIANT)
    path = path_reference(scene, 0.0, (16, 12), spp=16, variant=VARIANT)
    assert np.isfinite(direct).all() and (direct >= 0).all()
    assert len(cache_files(reference.cache_dir())) == 6
    assert not np.array_equal(direct, path)


# --- reference sets: both transports, noise floor ----------------------------------------------------

def test20_noise_floor_is_measured_between_two_seeds_and_stored_with_the_reference(monkeypatch):
    scene = tiny_scene()
    first = reference.reference_set(scene, 0.0, (16, 12), 64, "global", variant=VARIANT)
    second = reference.scene_reference(scene, 0.0, (16, 12), 64, reference.transport_integrator("global"),
                                       seed=reference.FLOOR_SEED, variant=VARIANT)
    assert first.reference.key != second.key  # two independent renders
    # the floor is every metric between the two renders, and it is stored in the cache beside them
    floor_files = [f for f in cache_files(reference.cache_dir()) if ".floor-" in f]
    assert len(floor_files) == 1 and floor_files[0].startswith(first.reference.key)
    assert 0.0 < first.floor["dssim"] < 0.5 and first.floor["psnr_db"] > 20.0
    monkeypatch.setattr(reference, "render_with_stderr", None)  # served from the cache, floor included
    again = reference.reference_set(scene, 0.0, (16, 12), 64, "global", variant=VARIANT)
    assert again.floor == pytest.approx(first.floor)


def test21_noise_corrected_error_is_near_zero_for_a_second_reference_and_positive_for_a_biased_image():
    from suite.core.metrics import rel_mse

    scene = tiny_scene()
    ref = reference.scene_reference(scene, 0.0, (16, 12), 256, reference.transport_integrator("direct"),
                                    variant=VARIANT)
    other = reference.scene_reference(scene, 0.0, (16, 12), 256, reference.transport_integrator("direct"), seed=7,
                                      variant=VARIANT)
    raw = rel_mse(ref.image, other.image)
    corrected = rel_mse(ref.image, other.image, ref_stderr=ref.stderr, test_stderr=other.stderr)
    # the uncorrected error of two equal-quality renders is their noise; the correction removes most of it
    assert raw > 0 and abs(corrected) < 0.25 * raw
    biased = rel_mse(ref.image, 1.1 * other.image, ref_stderr=ref.stderr, test_stderr=other.stderr)
    assert biased > 4 * abs(corrected) and biased > 0


def test22_unknown_light_transport_is_a_user_error():
    with pytest.raises(UserError, match="unknown light transport 'photon'"):
        reference.transport_integrator("photon")
