"""The à-trous filter and the bilateral spatial variance as Dr.Jit kernels (suite/core/device/denoise.py): the
values of the host filters (suite/core/denoise.py) on every Dr.Jit variant, llvm_ad_rgb here and cuda_ad_rgb where a
GPU is usable. The two paths do the same operations in the same order; the device's à-trous passes run in float32
(the host's weights and sums are float64) and Dr.Jit's ``exp`` (and ``pow`` for a fractional normal exponent) is its
own, so they agree to float32 rounding: the spatial variance within a few units in the last place, the à-trous
passes within 1e-5 relative."""
import numpy as np
import pytest

from suite.core import denoise
from suite.core.device import denoise as dden
from suite.core.trace import backend_params

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")
def _frame(h, w, seed=0):
    """Random colour and variance over guides with holes, a depth step, a crease and random normals."""
    rng = np.random.default_rng(seed)
    c = (rng.gamma(1.0, 1.0, (h, w, 3))).astype(np.float32)
    v = (rng.random((h, w)) * 0.3).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    z = (3.0 + 0.05 * xx + 2.0 * (xx > w // 2) + 0.1 * rng.random((h, w))).astype(np.float32)
    n = np.zeros((h, w, 3), np.float32)
    n[..., 2] = 1.0
    n[yy > h // 2] = (0.0, 0.6, 0.8)
    noisy = rng.random((h, w)) < 0.2
    rnd = rng.normal(size=(h, w, 3)).astype(np.float32)
    n[noisy] = (rnd / np.linalg.norm(rnd, axis=-1, keepdims=True))[noisy]
    valid = rng.random((h, w)) > 0.15
    return c, v, z, n, valid


def _close(a, b):
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=1e-7)


def _close32(a, b):
    """The float32 passes against the host's float64 weights and sums."""
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("radius, phi_normal, iterations, feedback",
                         [(1, 128.0, 5, 1), (2, 17.5, 3, 2), (1, 0.0, 7, 0)])
def test01_device_atrous_gives_the_host_filter(drjit_device, backend, radius, phi_normal, iterations, feedback):
    # 7 passes reach step 64, wider than the 47x33 image: those taps all leave it
    c, v, z, n, valid = _frame(33, 47, seed=radius)
    s = denoise.AtrousSettings(iterations=iterations, radius=radius, phi_normal=phi_normal, phi_depth=0.5,
                               phi_color=4.0)
    ref_c, ref_v, ref_tap = denoise.atrous(c, v, z, n, valid, s, feedback)
    out_c, out_v, out_tap = dden.atrous_arrays(drjit_device(backend), c, v, z, n, valid, s, feedback)
    assert out_c.dtype == np.float32 and out_c.shape == ref_c.shape
    _close32(out_c, ref_c)
    _close32(out_v, ref_v)
    assert (out_tap is None) == (ref_tap is None)
    if ref_tap is not None:
        _close32(out_tap, ref_tap)
    assert np.array_equal(out_c[~valid], c[~valid])                  # pixels without a surface pass through
    assert not np.allclose(out_c[valid], c[valid])                   # and the others were filtered


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("h, w", [(1, 1), (1, 6), (5, 1), (2, 3)])
def test02_images_smaller_than_the_kernel(drjit_device, backend, h, w):
    c, v, z, n, valid = _frame(h, w, seed=h * 10 + w)
    valid[:] = True
    s = denoise.AtrousSettings(iterations=3, radius=2)
    ref_c, ref_v, _ = denoise.atrous(c, v, z, n, valid, s)
    out_c, out_v, _ = dden.atrous_arrays(drjit_device(backend), c, v, z, n, valid, s)
    _close32(out_c, ref_c)
    _close32(out_v, ref_v)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("phi_normal, radius", [(128.0, 2), (17.5, 1)])
def test03_device_spatial_variance_gives_the_host_estimate(drjit_device, backend, phi_normal, radius):
    c, _, z, n, valid = _frame(29, 41, seed=7)
    lum = denoise.luminance(c)
    ref = denoise.spatial_variance(lum, z, n, valid, phi_normal, radius)
    out = dden.spatial_variance_arrays(drjit_device(backend), lum, z, n, valid, phi_normal, radius)
    _close(out, ref)
    assert (out[~valid] == 0).all() and (out[valid] > 0).any()


@pytest.mark.parametrize("backend", DRJIT)
def test04_the_device_filter_copies_count_their_bytes(drjit_device, backend):
    dev = drjit_device(backend)
    c, v, z, n, valid = _frame(10, 12)
    before = dict(dev.counters)
    dden.atrous_arrays(dev, c, v, z, n, valid, denoise.AtrousSettings(iterations=2), 1)
    up = dev.counters["bytes_to_device"] - before["bytes_to_device"]
    down = dev.counters["bytes_to_host"] - before["bytes_to_host"]
    px = 10 * 12
    assert up == px * (4 + 12 + 1) + px * (12 + 4)                  # depth, normals, validity; colour, variance
    assert down == px * (12 + 4 + 12)                                # colour, variance, the fed-back colour


@pytest.mark.parametrize("backend", DRJIT)
def test05_spatial_variance_of_some_pixels_is_the_whole_images_there_and_zero_elsewhere(drjit_device, backend):
    """``active``: the pixels that need the estimate (A-SVGF's short histories). They get the whole image's values
    bit for bit, the others 0, whether a packet holds a few such pixels or none (whole rows without any)."""
    c, _, z, n, valid = _frame(29, 41, seed=11)
    lum = denoise.luminance(c)
    dev = drjit_device(backend)
    frame = dden.DeviceFrame.from_host(dev, z, n, valid)
    lum_dev = dev.to_device(lum.reshape(-1), dev.Float)
    rng = np.random.default_rng(3)
    active = rng.random((29, 41)) < 0.1
    active[10:20] = False
    active[25] = True
    whole = dev.to_host(dden.spatial_variance(frame, lum_dev, 128.0, 2))
    some = dev.to_host(dden.spatial_variance(frame, lum_dev, 128.0, 2,
                                             active=dev.to_device(active.reshape(-1), dev.Bool)))
    a = active.reshape(-1)
    assert np.array_equal(some[a], whole[a]) and (some[~a] == 0).all()
    assert (whole[a & valid.reshape(-1)] > 0).any()
    _close(whole.reshape(29, 41), denoise.spatial_variance(lum, z, n, valid, 128.0, 2))
