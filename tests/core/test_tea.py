"""suite.core.tea: the host twins of Mitsuba's counter-based random numbers equal Mitsuba's bit for bit, so the host and
device area-light estimators take the same samples (tests/core/test_device.py test05)."""
import numpy as np
import pytest

from suite.core import tea
from suite.core.scene import load
from suite.core.trace import backend_params, make


@pytest.fixture(scope="module")
def mi_module(request):
    return make(request.param, load("cornell")).device.m


@pytest.mark.parametrize("mi_module", backend_params("mitsuba-llvm"), indirect=True)
def test01_tea_words_and_floats_equal_mitsubas(mi_module):
    rng = np.random.default_rng(0)
    v0 = rng.integers(0, 2**32, 100_000, dtype=np.uint64).astype(np.uint32)
    v1 = rng.integers(0, 2**32, 100_000, dtype=np.uint64).astype(np.uint32)
    v0[:4], v1[:4] = [0, 0xFFFFFFFF, 0, 1], [0, 0xFFFFFFFF, 0xFFFFFFFF, 0]  # the ends of the range
    m = mi_module
    words, got = tea.tea_arrays(v0, v1)
    assert np.array_equal(words, np.array(m.sample_tea_32(m.UInt32(v0), m.UInt32(v1))[0], np.uint32))
    floats = np.array(m.sample_tea_float32(m.UInt32(v0), m.UInt32(v1)), np.float32)
    assert np.array_equal(got.view(np.uint32), floats.view(np.uint32))
    assert got.min() >= 0.0 and got.max() < 1.0


@pytest.mark.parametrize("mi_module", backend_params("mitsuba-llvm"), indirect=True)
@pytest.mark.parametrize("size", [1, 2, 3, 16, 17, 100, 4097])
def test02_kensler_permutation_equals_mitsubas_and_permutes(mi_module, size):
    """Every size, powers of two and not (the cycle walk), with random seeds; for one seed the indices 0..size-1
    map onto 0..size-1 once each."""
    m = mi_module
    rng = np.random.default_rng(size)
    index = rng.integers(0, size, 20_000).astype(np.uint32)
    seed = rng.integers(0, 2**32, 20_000, dtype=np.uint64).astype(np.uint32)
    want = np.array(m.permute_kensler(m.UInt32(index), size, m.UInt32(seed)), np.uint32)
    assert np.array_equal(tea.permute_kensler_array(index, size, seed), want)
    all_of_them = tea.permute_kensler_array(np.arange(size, dtype=np.uint32), size, np.full(size, 12345, np.uint32))
    assert np.array_equal(np.sort(all_of_them), np.arange(size))
