"""Metrics: the display transform, SSIM/DSSIM/PSNR/NRMSE/FLIP definitions, and input checks."""
import math
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from suite.core import metrics
from suite.errors import UserError
from suite.core.metrics import compare, dssim, flip, nrmse, psnr, ssim, to_display


def srgb_decode(display):
    import colour

    return np.asarray(colour.cctf_decoding(np.asarray(display, np.float64), function="sRGB"), np.float64)


def random_image(seed, shape=(24, 32, 3), scale=1.0):
    return (np.random.default_rng(seed).random(shape) * scale).astype(np.float32)


# --- display transform ------------------------------------------------------------------------------

def test01_display_transform_is_srgb_of_clipped_linear():
    linear = np.array([-1.0, 0.0, 0.0031308, 0.5, 1.0, 7.0])
    expected = np.array([0.0, 0.0, 0.0031308 * 12.92, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0, 1.0])
    np.testing.assert_allclose(to_display(linear), expected, atol=1e-12)


def test02_exposure_is_a_linear_multiplier():
    linear = np.array([0.05, 0.1, 0.2, 0.4])
    np.testing.assert_allclose(to_display(linear, exposure=2.5), to_display(2.5 * linear), atol=0)


@pytest.mark.parametrize("exposure", [0.0, -1.0, float("nan"), float("inf"), "bright"])
def test03_invalid_exposure_is_a_user_error(exposure):
    with pytest.raises(UserError, match="exposure"):
        to_display(np.ones(3), exposure=exposure)


# --- identical and known perturbations --------------------------------------------------------------

def test04_identical_images_score_perfectly():
    img = random_image(1)
    assert compare(img, img) == {"ssim": 1.0, "dssim": 0.0, "psnr_db": math.inf, "nrmse": 0.0, "flip": 0.0,
                                 "rel_mse": 0.0}


@pytest.mark.parametrize("offset", [0.01, 0.05, 0.2])
def test05_constant_display_offset_gives_psnr_20_log10_of_inverse_offset(offset):
    # Display values in [0.1, 0.7] plus an offset stay below 1, so clipping cannot change the error.
    display_ref = 0.1 + 0.6 * np.random.default_rng(2).random((16, 16, 3))
    ref, test = srgb_decode(display_ref), srgb_decode(display_ref + offset)
    assert psnr(ref, test) == pytest.approx(20.0 * math.log10(1.0 / offset), abs=1e-6)


def test06_nrmse_is_relative_rms_error_of_linear_images():
    ref = random_image(3).astype(np.float64)
    assert nrmse(ref, 1.1 * ref) == pytest.approx(0.1, rel=1e-9)
    assert nrmse(2.0 * ref, ref) == pytest.approx(0.5, rel=1e-9)


def test07_metrics_follow_exposure_except_nrmse():
    ref, test = random_image(4, scale=3.0), random_image(5, scale=3.0)
    scaled = compare(4.0 * ref, 4.0 * test)
    exposed = compare(ref, test, exposure=4.0)
    for name in ("ssim", "dssim", "psnr_db", "flip"):
        assert exposed[name] == pytest.approx(scaled[name], rel=1e-5), name
    assert compare(ref, test, exposure=0.25)["nrmse"] == pytest.approx(exposed["nrmse"], rel=1e-12)


def test08_compare_matches_the_single_metrics():
    ref, test = random_image(6), random_image(7)
    result = compare(ref, test, exposure=1.5)
    assert result["ssim"] == ssim(ref, test, exposure=1.5)
    assert result["dssim"] == dssim(ref, test, exposure=1.5)
    assert result["psnr_db"] == psnr(ref, test, exposure=1.5)
    assert result["nrmse"] == nrmse(ref, test)
    assert result["flip"] == flip(ref, test, exposure=1.5)


def test09_larger_error_scores_worse_on_every_metric():
    ref = random_image(8)
    noise = np.random.default_rng(9).normal(size=ref.shape).astype(np.float32)
    small = compare(ref, np.clip(ref + 0.02 * noise, 0, None))
    large = compare(ref, np.clip(ref + 0.2 * noise, 0, None))
    assert large["ssim"] < small["ssim"] < 1.0
    assert large["dssim"] > small["dssim"] > 0.0
    assert large["psnr_db"] < small["psnr_db"] < math.inf
    assert large["nrmse"] > small["nrmse"] > 0.0
    assert large["flip"] > small["flip"] > 0.0


# --- constant images --------------------------------------------------------------------------------

def test10_equal_constant_images_score_perfectly():
    grey = np.full((16, 16, 3), 0.3)
    assert compare(grey, grey) == {"ssim": 1.0, "dssim": 0.0, "psnr_db": math.inf, "nrmse": 0.0, "flip": 0.0,
                                   "rel_mse": 0.0}


def test11_different_constant_images_give_finite_imperfect_scores():
    dark, light = np.full((16, 16, 3), 0.2), np.full((16, 16, 3), 0.5)
    result = compare(dark, light)
    assert all(math.isfinite(v) for v in result.values()), result
    a, b = float(to_display(0.2)), float(to_display(0.5))
    c1 = (0.01 * 1.0) ** 2  # (K1 * data_range)^2; the structure term is 1 without variance
    assert result["ssim"] == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-9)
    assert 0.0 < result["ssim"] < 1.0
    delta_display = b - a
    assert result["psnr_db"] == pytest.approx(20.0 * math.log10(1.0 / delta_display), abs=1e-9)
    assert result["nrmse"] == pytest.approx(1.5, rel=1e-12)
    assert result["flip"] > 0.0


def test12_black_reference_gives_zero_or_infinite_nrmse():
    black = np.zeros((16, 16, 3))
    assert nrmse(black, black) == 0.0
    assert nrmse(black, np.full_like(black, 0.1)) == math.inf


# --- algebraic properties ---------------------------------------------------------------------------

@settings(max_examples=20, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), scale=st.floats(0.01, 10.0), exposure=st.floats(0.1, 10.0))
def test13_dssim_is_half_of_one_minus_ssim(seed, scale, exposure):
    ref, test = random_image(seed, (12, 12, 3), scale), random_image(seed + 1, (12, 12, 3), scale)
    assert dssim(ref, test, exposure) == (1.0 - ssim(ref, test, exposure)) / 2.0
    result = compare(ref, test, exposure)
    assert result["dssim"] == (1.0 - result["ssim"]) / 2.0


@settings(max_examples=10, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1))
def test14_ssim_dssim_psnr_and_flip_are_symmetric(seed):
    a, b = random_image(seed, (12, 12, 3), 2.0), random_image(seed + 1, (12, 12, 3), 2.0)
    forward, backward = compare(a, b), compare(b, a)
    for name in ("ssim", "dssim", "psnr_db", "flip"):
        assert forward[name] == pytest.approx(backward[name], rel=1e-12, abs=1e-12), name


def test15_gray_image_equals_its_rgb_repetition():
    gray_ref, gray_test = random_image(10, (16, 16)), random_image(11, (16, 16))
    rgb = compare(np.repeat(gray_ref[..., None], 3, axis=2), np.repeat(gray_test[..., None], 3, axis=2))
    assert compare(gray_ref, gray_test) == rgb
    assert compare(gray_ref[..., None], gray_test[..., None]) == rgb


# --- bad input ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad_value, count", [(np.nan, 1), (np.inf, 2), (-np.inf, 3)])
def test16_non_finite_test_image_is_a_user_error_naming_it(bad_value, count):
    ref, test = random_image(12), random_image(13)
    test.reshape(-1)[:count] = bad_value
    with pytest.raises(UserError, match=f"image 'test' contains {count} NaN/Inf values"):
        compare(ref, test)


def test17_non_finite_reference_is_reported_with_the_callers_name():
    ref = random_image(14)
    ref[3, 4, 1] = np.nan
    for metric in (compare, ssim, dssim, psnr, nrmse, flip):
        with pytest.raises(UserError, match="image 'ref.exr' contains 1 NaN/Inf values"):
            metric(ref, random_image(15), names=("ref.exr", "out.exr"))


def test18_shape_mismatch_is_a_user_error_naming_both_shapes():
    with pytest.raises(UserError, match=r"\(24, 32, 3\).*\(32, 24, 3\)"):
        compare(random_image(16), random_image(17, (32, 24, 3)))


@pytest.mark.parametrize("shape", [(16, 16, 4), (16, 16, 2), (16,), (2, 16, 16, 3), (0, 16, 3)])
def test19_unsupported_image_shapes_are_user_errors(shape):
    img = np.zeros(shape, np.float32)
    with pytest.raises(UserError, match="image 'reference'"):
        compare(img, img)


def test20_images_smaller_than_the_ssim_window_are_user_errors():
    tiny = random_image(18, (8, 32, 3))
    with pytest.raises(UserError, match="11x11"):
        ssim(tiny, tiny)
    # Metrics without a window still work on them.
    assert psnr(tiny, tiny) == math.inf


def test21_flip_exit_becomes_a_user_error(monkeypatch):
    import flip_evaluator

    def exiting_evaluate(*args, **kwargs):
        sys.exit(1)

    monkeypatch.setattr(flip_evaluator, "evaluate", exiting_evaluate)
    with pytest.raises(UserError, match="FLIP"):
        flip(random_image(19), random_image(20))


def test22_flip_uses_the_stated_viewing_condition(monkeypatch):
    import flip_evaluator

    seen = {}
    real_evaluate = flip_evaluator.evaluate

    def recording_evaluate(reference, test, dynamic_range, **kwargs):
        seen.update(kwargs, dynamic_range=dynamic_range, contiguous=reference.flags.c_contiguous,
                    dtype=reference.dtype)
        return real_evaluate(reference, test, dynamic_range, **kwargs)

    monkeypatch.setattr(flip_evaluator, "evaluate", recording_evaluate)
    flip(random_image(21)[:, ::-1], random_image(22))
    assert seen["dynamic_range"] == "LDR" and seen["inputsRGB"] is True
    assert seen["parameters"] == metrics.FLIP_VIEWING_CONDITION
    assert seen["contiguous"] and seen["dtype"] == np.float32


# --- noise-corrected relative MSE -----------------------------------------------------------------------

def test23_rel_mse_without_noise_estimates_is_mean_squared_error_over_squared_reference_plus_eps():
    ref, test = random_image(1), random_image(2)
    expected = np.mean((test.astype(np.float64) - ref) ** 2 / (ref.astype(np.float64) ** 2 + metrics.REL_MSE_EPS))
    assert metrics.rel_mse(ref, test) == pytest.approx(expected, rel=1e-9)
    assert compare(ref, test)["rel_mse"] == pytest.approx(expected, rel=1e-9)
    assert metrics.rel_mse(ref, ref) == 0.0


def test24_noise_correction_removes_the_references_known_variance():
    rng = np.random.default_rng(5)
    truth = random_image(3, shape=(64, 64, 3)) + 0.2
    sigma = 0.02
    noisy_ref = truth + rng.normal(0.0, sigma, truth.shape)
    stderr = np.full(truth.shape, sigma)
    raw = metrics.rel_mse(noisy_ref, truth)
    corrected = metrics.rel_mse(noisy_ref, truth, ref_stderr=stderr)
    # a perfect test image scores the reference's noise without correction, about 0 with it
    assert raw > 1e-4 and abs(corrected) < 0.1 * raw
    # a biased image keeps its error: within 10 % of its error against the noise-free truth (the noisy
    # reference in the denominator leaves a bias of second order in its relative noise)
    biased = 1.2 * truth
    assert metrics.rel_mse(noisy_ref, biased, ref_stderr=stderr) == pytest.approx(metrics.rel_mse(truth, biased),
                                                                                   rel=0.1)
    # an unknown (infinite) standard error means no correction
    assert metrics.rel_mse(noisy_ref, truth, ref_stderr=np.full(truth.shape, np.inf)) == raw
