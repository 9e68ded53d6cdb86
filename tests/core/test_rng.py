"""suite.core.rng: the host twins of Mitsuba's counter-based random numbers equal Mitsuba's bit for bit, so the host and
device area-light estimators take the same samples (tests/core/test_device.py test05)."""
import numpy as np
import pytest

from suite.core import rng
from suite.core.scene import load
from suite.core.trace import backend_params, make


@pytest.fixture(scope="module")
def mi_module(request):
    return make(request.param, load("cornell")).device.m


@pytest.mark.parametrize("mi_module", backend_params("mitsuba-llvm"), indirect=True)
def test01_tea_words_and_floats_equal_mitsubas_for_4_and_8_rounds(mi_module):
    gen = np.random.default_rng(0)
    v0 = gen.integers(0, 2**32, 100_000, dtype=np.uint64).astype(np.uint32)
    v1 = gen.integers(0, 2**32, 100_000, dtype=np.uint64).astype(np.uint32)
    v0[:4], v1[:4] = [0, 0xFFFFFFFF, 0, 1], [0, 0xFFFFFFFF, 0xFFFFFFFF, 0]  # the ends of the range
    m = mi_module
    for rounds in (4, 8):
        words, got = rng.tea_arrays(v0, v1, rounds)
        assert np.array_equal(words, np.array(m.sample_tea_32(m.UInt32(v0), m.UInt32(v1))[0], np.uint32))
        floats = np.array(m.sample_tea_float32(m.UInt32(v0), m.UInt32(v1), rounds), np.float32)
        assert np.array_equal(got.view(np.uint32), floats.view(np.uint32))
        assert got.min() >= 0.0 and got.max() < 1.0


@pytest.mark.parametrize("mi_module", backend_params("mitsuba-llvm"), indirect=True)
@pytest.mark.parametrize("size", [1, 2, 3, 16, 17, 100, 4097])
def test02_kensler_permutation_equals_mitsubas_and_permutes(mi_module, size):
    """Every size, powers of two and not (the cycle walk), with random seeds; for one seed the indices 0..size-1
    map onto 0..size-1 once each."""
    m = mi_module
    gen = np.random.default_rng(size)
    index = gen.integers(0, size, 20_000).astype(np.uint32)
    seed = gen.integers(0, 2**32, 20_000, dtype=np.uint64).astype(np.uint32)
    want = np.array(m.permute_kensler(m.UInt32(index), size, m.UInt32(seed)), np.uint32)
    assert np.array_equal(rng.permute_kensler_array(index, size, seed), want)
    all_of_them = rng.permute_kensler_array(np.arange(size, dtype=np.uint32), size, np.full(size, 12345, np.uint32))
    assert np.array_equal(np.sort(all_of_them), np.arange(size))


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
def test03_pcg_numbers_equal_on_host_and_device(backend):
    """The PCG hash and the path tracer's numbers (lane key, dimension) are integer operations: the host's numba,
    the host's numpy and the device's kernel give the same bits on every variant; the numbers lie in [0, 1), have
    24 random bits and look uniform (mean and variance of 100 k of them)."""
    from suite.core.device import rng as device_rng

    dev = make(backend, load("cornell")).device
    gen = np.random.default_rng(4)
    keys = gen.integers(0, 2**32, 100_000, dtype=np.uint64).astype(np.uint32)
    keys[:3] = [0, 1, 0xFFFFFFFF]
    want = np.array(device_rng.pcg(dev, dev.UInt32(keys)), np.uint32)
    assert np.array_equal(rng.pcg_np(keys), want)
    dims = np.array([0, 1, 7, 8, 40, 1 << 20])
    host = rng.hashed_uniforms(keys.astype(np.int64), rng.pcg_np(12345), rng.dim_hashes(dims))
    lane = device_rng.lane_keys(dev, dev.UInt32(keys), dev.UInt32(int(rng.pcg_np(12345))))
    for j, h in enumerate(rng.dim_hashes(dims)):
        got = np.array(device_rng.uniform(dev, lane, dev.UInt32(int(h))), np.float64)
        assert np.array_equal(host[:, j], got)
    assert host.min() >= 0.0 and host.max() < 1.0
    assert np.array_equal(host * 2**24, np.floor(host * 2**24))
    assert np.allclose(host.mean(axis=0), 0.5, atol=0.005) and np.allclose(host.var(axis=0), 1 / 12, atol=0.002)
    assert not np.array_equal(host[:, 0], host[:, 1])
