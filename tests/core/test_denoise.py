"""The shared edge-avoiding a-trous filter (suite.core.denoise): it removes noise where the guides say the surface
is continuous, stops at normal, depth and luminance edges, leaves pixels without a surface alone, and counts its
taps."""
import numpy as np
import pytest

from suite.core import denoise

H, W = 24, 32


def _flat(depth=2.0):
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = 1.0
    return np.full((H, W), depth, np.float32), normal, np.ones((H, W), bool)


def _noisy(level=0.5, sigma=0.2, seed=0):
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, sigma, (H, W, 1)).astype(np.float32)
    return np.clip(level + noise, 0, None) * np.ones((1, 1, 3), np.float32)


def test01_noise_on_a_continuous_surface_is_removed_and_the_mean_kept():
    depth, normal, valid = _flat()
    img = _noisy()
    var = denoise.spatial_variance(denoise.luminance(img), depth, normal, valid)
    out, out_var, _ = denoise.atrous(img, var, depth, normal, valid)
    err_in = np.mean((img - 0.5) ** 2)
    err_out = np.mean((out - 0.5) ** 2)
    assert err_out < err_in / 5
    assert abs(out.mean() - img.mean()) < 0.02
    assert out_var.mean() < var.mean() / 5  # the variance is filtered with the squared weights


def _two_halves(kind):
    depth, normal, valid = _flat()
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    img = np.where(left[..., None], 0.2, 0.8).astype(np.float32) * np.ones((1, 1, 3), np.float32)
    var = np.full((H, W), 0.01, np.float32)
    if kind == "normal":
        normal[~left] = (1.0, 0.0, 0.0)
    elif kind == "depth":
        depth[~left] = 20.0
    elif kind == "luminance":
        var[:] = 1e-6  # almost no noise: a luminance step is a real edge
    return img, var, depth, normal, valid, left


@pytest.mark.parametrize("kind", ["normal", "depth", "luminance"])
def test02_the_filter_does_not_blur_across_an_edge_of_its_guides(kind):
    img, var, depth, normal, valid, left = _two_halves(kind)
    out, _, _ = denoise.atrous(img, var, depth, normal, valid)
    if kind == "depth":
        # the two columns on the step have the step as their |grad z| (SVGF eq. 3 measures depth differences in
        # units of the local depth gradient), so only they may mix; every other pixel keeps its side
        left[:, W // 2 - 1: W // 2 + 1] = False
        right = ~left
        right[:, W // 2 - 1: W // 2 + 1] = False
    else:
        right = ~left
    assert np.abs(out[left] - 0.2).max() < 0.02 and np.abs(out[right] - 0.8).max() < 0.02


def test03_without_edges_in_the_guides_a_step_in_a_noisy_image_is_blurred():
    # the control of test02: the same step with noise-level variance and continuous guides does get filtered
    img, var, depth, normal, valid, left = _two_halves("none")
    var[:] = 0.2
    out, _, _ = denoise.atrous(img, var, depth, normal, valid)
    assert np.abs(out[:, W // 2 - 1] - 0.2).max() > 0.05


def test04_pixels_without_a_surface_pass_through_and_are_never_taps():
    depth, normal, valid = _flat()
    valid[:, :4] = False
    img = _noisy()
    img[:, :4] = 100.0  # would dominate any neighbour that took it as a tap
    out, _, _ = denoise.atrous(img, np.full((H, W), 0.04, np.float32), depth, normal, valid)
    assert np.array_equal(out[:, :4], img[:, :4]) and out[:, 4:].max() < 2.0


def test05_taps_radius_and_feedback():
    s = denoise.AtrousSettings(iterations=3, radius=2)
    assert denoise.atrous_taps(W, H, s) == W * H * 25 * 3
    depth, normal, valid = _flat()
    img = _noisy()
    var = denoise.spatial_variance(denoise.luminance(img), depth, normal, valid)
    out, _, tap = denoise.atrous(img, var, depth, normal, valid, s, feedback_tap=1)
    assert tap is not None and not np.array_equal(tap, out)
    with pytest.raises(ValueError, match="radius must be 1 or 2"):
        denoise.kernel(3)


def test06_helpers_shift_blur_and_estimate_variance():
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert denoise.shifted(a, 1, 0)[0, 0] == a[1, 0] and denoise.shifted(a, 1, 0)[2, 0] == 0
    ones = np.ones((5, 5), np.float32)
    assert denoise.gaussian3x3(ones)[2, 2] == pytest.approx(1.0) and denoise.gaussian3x3(ones)[0, 0] < 1.0
    depth, normal, valid = _flat()
    assert denoise.spatial_variance(np.full((H, W), 3.0), depth, normal, valid).max() == pytest.approx(0.0, abs=1e-6)
    noise = np.random.default_rng(1).normal(0, 0.5, (H, W))
    assert denoise.spatial_variance(noise, depth, normal, valid).mean() == pytest.approx(0.25, rel=0.25)
    # taps across a normal edge are not in the estimate: two flat halves of different level have no variance
    normal[:, W // 2:] = (1.0, 0.0, 0.0)
    step = np.where(np.arange(W) < W // 2, 0.0, 1.0)[None, :] * np.ones((H, 1))
    assert denoise.spatial_variance(step, depth, normal, valid).max() == pytest.approx(0.0, abs=1e-6)
    assert denoise.spatial_variance(step, depth, _flat()[1], valid).max() > 0.1


@pytest.mark.parametrize("radius, phi_normal, step", [(1, 128.0, 1), (1, 128.0, 8), (2, 17.5, 2), (2, 0.0, 64)])
def test07_the_compiled_pass_gives_the_bits_of_the_numpy_reference(radius, phi_normal, step):
    # atrous_pass (numba, parallel over rows) and atrous_pass_reference (numpy over whole images) do every float
    # operation in the same order and precision: random guides with holes, whole and fractional normal exponents,
    # steps that leave the image
    rng = np.random.default_rng(radius * 100 + step)
    h, w = 19, 27
    c = (rng.random((h, w, 3)) * 2.0).astype(np.float32)
    v = (rng.random((h, w)) * 0.3).astype(np.float32)
    z = (rng.random((h, w)) * 5.0 + 1.0).astype(np.float32)
    n = rng.normal(size=(h, w, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    valid = rng.random((h, w)) > 0.15
    fw = np.maximum(denoise.depth_fwidth(z, valid), 1e-8).astype(np.float32)
    s = denoise.AtrousSettings(radius=radius, phi_normal=phi_normal, phi_depth=0.5, phi_color=4.0)
    ref_c, ref_v = denoise.atrous_pass_reference(c, v, z, n, fw, valid, step, s)
    out_c, out_v = denoise.atrous_pass(c, v, z, n, fw, valid, step, s)
    assert out_c.dtype == np.float32 and out_v.dtype == np.float32
    assert np.array_equal(out_c, ref_c) and np.array_equal(out_v, ref_v)


@pytest.mark.parametrize("radius, phi_normal", [(2, 128.0), (1, 17.5), (2, 0.0)])
def test08_spatial_variance_of_some_pixels_has_the_bits_of_the_whole_image(radius, phi_normal):
    # the compiled pass gives the bits of the whole-image numpy expressions, over every pixel or over ``active``
    # ones (A-SVGF's short histories; 0 elsewhere): random guides with holes and a depth step, whole and
    # fractional normal exponents, an image edge in every window of the border pixels, a NaN luminance and a NaN
    # normal
    rng = np.random.default_rng(int(phi_normal) + radius)
    h, w = 23, 31
    lum = (rng.gamma(1.0, 1.0, (h, w))).astype(np.float32)
    lum[5, 7] = np.nan
    z = (rng.random((h, w)) * 0.05 + 2.0 + 3.0 * (np.arange(w) > w // 2)).astype(np.float32)
    n = rng.normal(size=(h, w, 3)).astype(np.float32)
    n[rng.random((h, w)) < 0.6] = (0.0, 0.0, 1.0)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[9, 12] = np.nan
    valid = rng.random((h, w)) > 0.15
    valid[9, 12] = valid[9, 13] = True
    active = rng.random((h, w)) < 0.3
    active[9, 13] = True
    active[0] = active[:, -1] = True
    whole = denoise.spatial_variance_reference(lum, z, n, valid, phi_normal, radius)
    some = denoise.spatial_variance(lum, z, n, valid, phi_normal, radius, active=active)
    every = denoise.spatial_variance(lum, z, n, valid, phi_normal, radius)
    assert some.dtype == np.float32 and every.dtype == np.float32
    same = lambda a, b: (a == b) | (np.isnan(a) & np.isnan(b))  # noqa: E731
    assert same(every, whole).all()
    assert same(some, whole)[active].all() and (some[~active] == 0).all()
    assert np.isnan(whole).any() and (whole[active & valid] > 0).any()


@pytest.mark.parametrize("h, w", [(1, 1), (2, 5), (5, 2)])
def test09_spatial_variance_of_images_smaller_than_the_window(h, w):
    rng = np.random.default_rng(h * 10 + w)
    lum = rng.random((h, w)).astype(np.float32)
    z = (rng.random((h, w)) * 0.01 + 2.0).astype(np.float32)
    n = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (h, w, 1))
    valid = np.ones((h, w), bool)
    ref = denoise.spatial_variance_reference(lum, z, n, valid)
    assert np.array_equal(denoise.spatial_variance(lum, z, n, valid), ref)
    assert (ref > 0).any() or h * w == 1
