"""Image-quality metrics between a reference and a test image, after one documented display transform.

Inputs are linear HDR images (radiance), numpy arrays of shape ``(H, W, 3)``; a gray ``(H, W)`` or
``(H, W, 1)`` image is repeated into three channels. Reference and test must have the same shape and only
finite values. See ``docs/metrics.md`` for the definitions and the edge cases.

Display transform (:func:`to_display`), used by SSIM, DSSIM, PSNR, FLIP and PNG output::

    display = sRGB_encode(clip(exposure * linear, 0, 1))        # in [0, 1]

``exposure`` is a linear multiplier (2.0 = one stop brighter), not a number of stops. The sRGB encoding is
IEC 61966-2-1 as implemented by colour-science (``colour.cctf_encoding(x, function="sRGB")``).

NRMSE and the relative MSE are the exceptions: they are computed on the linear images, because they measure
radiance error, which clipping and the sRGB curve would hide in bright regions and exaggerate in dark ones.

The relative MSE (:func:`rel_mse`) is the suite's primary error against a Monte Carlo reference: with the
reference's per-pixel standard error it is **noise-corrected** (its expected value is the error of the test
against the noise-free image, not against one noisy render), so methods can be ranked below the reference's own
noise floor.
"""
from __future__ import annotations

import math

import numpy as np

from suite.errors import UserError

# SSIM settings of Wang, Bovik, Sheikh and Simoncelli (2004), "Image quality assessment: from error
# visibility to structural similarity": an 11x11 Gaussian window with sigma 1.5, population covariances,
# K1 = 0.01 and K2 = 0.03 (scikit-image's defaults) on images with a data range of 1.
SSIM_SETTINGS = {
    "gaussian_weights": True,
    "sigma": 1.5,
    "use_sample_covariance": False,
    "data_range": 1.0,
    "K1": 0.01,
    "K2": 0.03,
}
# With a Gaussian window scikit-image uses win_size = 2 * int(3.5 * sigma + 0.5) + 1.
SSIM_MIN_SIZE_PX = 2 * int(3.5 * SSIM_SETTINGS["sigma"] + 0.5) + 1

# LDR-FLIP viewing condition of the FLIP paper (Andersson et al. 2020): 0.7 m from a 0.7 m wide display
# that is 3840 pixels wide, about 67 pixels per degree. Stated here so results never follow a package default.
FLIP_VIEWING_CONDITION = {"vc": [0.7, 3840.0, 0.7]}  # [distance m, display width px, display width m]

DEFAULT_NAMES = ("reference", "test")
# Relative MSE denominator offset (Rousselle, Knaus and Zwicker 2011, "Adaptive sampling and reconstruction using
# greedy error minimization", relMSE = mean((test - ref)^2 / (ref^2 + eps))): keeps black pixels from dominating.
REL_MSE_EPS = 0.01


def _srgb_encode():
    # colour-science takes seconds to import; load it on first use so that importing the suite stays quick.
    import colour

    return lambda x: colour.cctf_encoding(x, function="sRGB")


def _check_exposure(exposure: float) -> float:
    try:
        value = float(exposure)
    except (TypeError, ValueError):
        raise UserError(f"exposure must be a number, got {exposure!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise UserError(f"exposure must be a finite linear multiplier > 0, got {exposure!r}")
    return value


def _check_finite(img: np.ndarray, name: str) -> None:
    finite = np.isfinite(img)
    if not finite.all():
        bad = int(finite.size - np.count_nonzero(finite))
        raise UserError(f"image '{name}' contains {bad} NaN/Inf values")


def _as_rgb(img, name: str) -> np.ndarray:
    """float64 (H, W, 3) copy of one input image, or UserError naming what is wrong with it."""
    arr = np.asarray(img)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise UserError(f"image '{name}' has non-numeric dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3):
        raise UserError(f"image '{name}' has shape {np.shape(img)}; expected (H, W, 3) RGB or (H, W) gray")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise UserError(f"image '{name}' is empty (shape {np.shape(img)})")
    _check_finite(arr, name)
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return arr


def _check_pair(ref, test, names) -> tuple[np.ndarray, np.ndarray]:
    ref_name, test_name = names
    if np.shape(ref) != np.shape(test):
        raise UserError(f"image '{ref_name}' has shape {np.shape(ref)} but image '{test_name}' has shape "
                        f"{np.shape(test)}; they must match")
    return _as_rgb(ref, ref_name), _as_rgb(test, test_name)


def to_display(img, exposure: float = 1.0) -> np.ndarray:
    """The display transform: linear HDR → ``exposure`` × → clip to [0, 1] → sRGB encoding.

    Works elementwise on any shape; returns float64 values in [0, 1]. Negative values (which a renderer should
    not produce) clip to black. Does not check for NaN/Inf; the metrics do that before calling it.
    """
    scale = _check_exposure(exposure)
    linear = np.clip(np.asarray(img, dtype=np.float64) * scale, 0.0, 1.0)
    return np.clip(np.asarray(_srgb_encode()(linear), dtype=np.float64), 0.0, 1.0)


def _ssim_display(ref_display: np.ndarray, test_display: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    height, width = ref_display.shape[:2]
    if min(height, width) < SSIM_MIN_SIZE_PX:
        raise UserError(f"images are {width}x{height} pixels; SSIM needs at least "
                        f"{SSIM_MIN_SIZE_PX}x{SSIM_MIN_SIZE_PX} for its Gaussian window")
    return float(structural_similarity(ref_display, test_display, channel_axis=-1, **SSIM_SETTINGS))


def _psnr_display(ref_display: np.ndarray, test_display: np.ndarray) -> float:
    mse = float(np.mean((ref_display - test_display) ** 2))
    if mse == 0.0:
        return math.inf
    # The peak is 1: display images live in [0, 1].
    return 10.0 * math.log10(1.0 / mse)


def _nrmse_linear(ref: np.ndarray, test: np.ndarray) -> float:
    error_rms = math.sqrt(float(np.mean((test - ref) ** 2)))
    ref_rms = math.sqrt(float(np.mean(ref ** 2)))
    if error_rms == 0.0:
        return 0.0
    if ref_rms == 0.0:
        # Any error relative to an all-black reference is unbounded.
        return math.inf
    return error_rms / ref_rms


def _flip_display(ref_display: np.ndarray, test_display: np.ndarray) -> float:
    import flip_evaluator

    # flip-evaluator wants C-contiguous float32 HxWx3 in [0, 1] and calls sys.exit() on some bad input; the
    # inputs are validated before this point, and any exit it still takes becomes a UserError.
    ref32 = np.ascontiguousarray(ref_display, dtype=np.float32)
    test32 = np.ascontiguousarray(test_display, dtype=np.float32)
    try:
        _, mean_error, _ = flip_evaluator.evaluate(ref32, test32, "LDR", inputsRGB=True, applyMagma=False,
                                                   computeMeanError=True,
                                                   parameters=dict(FLIP_VIEWING_CONDITION))
    except SystemExit as exc:
        raise UserError(f"FLIP evaluation failed (flip-evaluator exited with status {exc.code})") from None
    except (RuntimeError, ValueError, TypeError) as exc:
        raise UserError(f"FLIP evaluation failed: {exc}") from None
    return float(mean_error)


def ssim(ref, test, exposure: float = 1.0, names=DEFAULT_NAMES) -> float:
    """Mean SSIM of the display images (1 = identical), averaged over the three channels.

    Settings: :data:`SSIM_SETTINGS` (Wang et al. 2004). Both images must be at least 11x11 pixels.
    """
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    return _ssim_display(to_display(ref_rgb, exposure), to_display(test_rgb, exposure))


def dssim(ref, test, exposure: float = 1.0, names=DEFAULT_NAMES) -> float:
    """Structural dissimilarity (1 − SSIM) / 2: 0 for identical images."""
    return (1.0 - ssim(ref, test, exposure, names)) / 2.0


def psnr(ref, test, exposure: float = 1.0, names=DEFAULT_NAMES) -> float:
    """PSNR in dB of the display images with peak 1: ``10 log10(1 / MSE)``; ``inf`` for identical images."""
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    return _psnr_display(to_display(ref_rgb, exposure), to_display(test_rgb, exposure))


def nrmse(ref, test, names=DEFAULT_NAMES) -> float:
    """RMS of (test − ref) over the RMS of ref, on the linear images (exposure does not change it).

    0 for identical images (also two black ones); ``inf`` when the reference is all black and the test is not.
    Not symmetric: the reference sets the scale.
    """
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    return _nrmse_linear(ref_rgb, test_rgb)


def flip(ref, test, exposure: float = 1.0, names=DEFAULT_NAMES) -> float:
    """Mean LDR-FLIP error of the display images (0 = identical, at most 1).

    Viewing condition: :data:`FLIP_VIEWING_CONDITION` (about 67 pixels per degree).
    """
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    return _flip_display(to_display(ref_rgb, exposure), to_display(test_rgb, exposure))


def rel_mse(ref, test, ref_stderr=None, test_stderr=None, names=DEFAULT_NAMES) -> float:
    """Relative MSE of the linear images, noise-corrected when standard errors are given::

        rel_mse = mean( ((test - ref)^2 - ref_stderr^2 - test_stderr^2) / (ref^2 + REL_MSE_EPS) )

    over pixels and channels. For a reference ``ref`` = truth + noise of variance ``ref_stderr^2`` (and a test
    with its own independent noise), ``E[(test - ref)^2] = (test - truth)^2 + var(ref) + var(test)``: subtracting
    the variances leaves an estimate of the test's error against the noise-free image. The estimate may be
    slightly negative when the test is as good as the reference (noise); it is not clamped, so averages stay
    unbiased. A non-finite standard error (unknown: a one-pass reference) counts as 0 (no correction).
    """
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    return _rel_mse_linear(ref_rgb, test_rgb, ref_stderr, test_stderr)


def _variance(stderr, shape) -> np.ndarray | float:
    if stderr is None:
        return 0.0
    s = np.asarray(stderr, dtype=np.float64)
    if s.ndim == 2:
        s = s[:, :, None]
    s = np.broadcast_to(s, shape)
    return np.where(np.isfinite(s), s * s, 0.0)


def _rel_mse_linear(ref: np.ndarray, test: np.ndarray, ref_stderr=None, test_stderr=None) -> float:
    sq = (test - ref) ** 2 - _variance(ref_stderr, ref.shape) - _variance(test_stderr, ref.shape)
    return float(np.mean(sq / (ref * ref + REL_MSE_EPS)))


def compare(ref, test, exposure: float = 1.0, names=DEFAULT_NAMES, ref_stderr=None,
            test_stderr=None) -> dict[str, float]:
    """All metrics at once: ``{"ssim", "dssim", "psnr_db", "nrmse", "flip", "rel_mse"}`` (inputs checked once);
    ``rel_mse`` is noise-corrected with the standard errors when they are given (:func:`rel_mse`)."""
    ref_rgb, test_rgb = _check_pair(ref, test, names)
    ref_display = to_display(ref_rgb, exposure)
    test_display = to_display(test_rgb, exposure)
    ssim_value = _ssim_display(ref_display, test_display)
    return {
        "ssim": ssim_value,
        "dssim": (1.0 - ssim_value) / 2.0,
        "psnr_db": _psnr_display(ref_display, test_display),
        "nrmse": _nrmse_linear(ref_rgb, test_rgb),
        "flip": _flip_display(ref_display, test_display),
        "rel_mse": _rel_mse_linear(ref_rgb, test_rgb, ref_stderr, test_stderr),
    }
