"""The per-pixel RNG: numpy and numba give the same bits, numbers lie in [0, 1), and every frame draws fresh
seeds (not a permutation of the previous frame's)."""
import numba
import numpy as np

from methods.quake_drt import direct, rng


@numba.njit
def _uniform_nb(seeds, dim):
    out = np.empty(seeds.shape[0])
    for i in range(seeds.shape[0]):
        out[i] = direct.uniform_nb(seeds[i], dim)
    return out


def test01_numpy_and_numba_hashes_agree_bit_for_bit():
    seeds = rng.pcg_np(np.arange(50000, dtype=np.uint32))
    for dim in (0, 1, rng.DIM_LIGHTS, rng.DIM_LIGHTS + 4 * 1000, 2 ** 32 - 1):
        assert np.array_equal(rng.uniform_np(seeds, dim), _uniform_nb(seeds, dim))


def test02_uniform_numbers_lie_in_the_unit_interval_and_times_n_stay_below_n():
    u = rng.uniform_np(rng.pcg_np(np.arange(200000, dtype=np.uint32)), 7)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert (np.floor(u * 97) < 97).all()
    counts = np.bincount(np.floor(u * 16).astype(int), minlength=16)
    assert np.abs(counts / counts.mean() - 1).max() < 0.03


def test03_consecutive_frames_draw_new_seeds():
    a = rng.pixel_seeds(100, 64, 32).reshape(-1)
    b = rng.pixel_seeds(101, 64, 32).reshape(-1)
    assert len(np.unique(a)) == a.size
    assert len(np.intersect1d(a, b)) < 5  # not the same set of seeds shuffled across pixels
    assert np.array_equal(a, rng.pixel_seeds(100, 64, 32).reshape(-1))
