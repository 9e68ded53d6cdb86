"""Light subsampling (rt_numRandomDL) is unbiased: the mean of many k-light frames equals the all-lights image
within its standard error, for uniform and power-proportional choice, and the choice itself is uniform (or
proportional to power) over every light of a row, the first and the last included."""
import numpy as np
import pytest

from methods.quake_drt import direct

N_FRAMES = 96


def _blocks(img, b=4):
    """Means of b x b pixel blocks (the last axis kept): a pixel's light choice is a rare-event draw (one light
    in 25 per frame), so its own mean over 96 frames is far from normal; a block of 16 pixels, which choose
    independently, is."""
    img = np.asarray(img, np.float64)
    lead, (h, w, c) = img.shape[:-3], img.shape[-3:]
    return img.reshape(*lead, h // b, b, w // b, b, c).mean(axis=(-4, -2))


def _z_outliers(stack, ref, ref_stack=None, limit=4.5):
    """Fraction of 4x4-block channels whose mean over the frames of ``stack`` differs from ``ref`` by more than
    ``limit`` standard errors (of both, when ``ref`` is the mean of ``ref_stack``), and the z-score of the whole
    image's mean."""
    n = len(stack)
    blocks = _blocks(stack)
    mean = blocks.mean(axis=0)
    se = blocks.std(axis=0, ddof=1) / np.sqrt(n)
    if ref_stack is not None:
        rb = _blocks(ref_stack)
        ref = rb.mean(axis=0)
        se = np.sqrt(se ** 2 + (rb.std(axis=0, ddof=1) / np.sqrt(len(rb))) ** 2)
    else:
        ref = _blocks(ref)
    tested = se > 1e-7 * max(ref.max(), 1e-12)
    z = np.where(tested, (mean - ref) / np.where(tested, se, 1.0), 0.0)
    frame_means = stack.reshape(n, -1).mean(axis=1)
    global_se = frame_means.std(ddof=1) / np.sqrt(n)
    z_global = (frame_means.mean() - ref.mean()) / max(global_se, 1e-12)
    exact = ~tested & (np.abs(mean - ref) > 1e-6 * max(ref.max(), 1e-12))  # no noise but a different value
    return float((np.abs(z) > limit).mean()), float(z_global), int(exact.sum())


@pytest.fixture
def many_lights(two_rooms):
    # Door open, so every light of both rooms is a candidate of every pixel: 24 point lights and an area light.
    return two_rooms(door_open=True, lights_in_b=2, extra_lights=20, camera="a")


@pytest.mark.parametrize("k,mode", [(1, "uniform"), (5, "uniform"), (2, "power"), (1, "irradiance")])
def test01_k_light_mean_equals_the_all_lights_image_within_its_standard_error(renderer, many_lights, k, mode):
    scene, vis = many_lights
    # Hard shadows make the all-lights image exact (no random numbers), so the only noise is the light choice.
    ref = renderer(scene, vis, soft_shadows=False, num_random_dl=0).raw()[0]
    r = renderer(scene, vis, soft_shadows=False, num_random_dl=k, light_sampling=mode)
    stack = r.raw_stack(N_FRAMES)
    assert stack.std(axis=0).max() > 0  # it is noisy: a subsample, not all lights
    outliers, z_global, exact = _z_outliers(stack, ref)
    assert outliers < 0.01, f"{100 * outliers:.2f} % of block channels off by more than 4.5 standard errors"
    assert abs(z_global) < 4.5, f"image mean off by {z_global:.1f} standard errors"
    assert exact == 0


def test02_the_integer_division_weight_of_the_public_code_would_fail_the_check(renderer, many_lights):
    """The check above is sharp enough to catch the public code's defect: uint / uint weights (5 lights
    subsampled to 2 weigh 2 instead of 2.5; here 25 candidates subsampled to 5... 4 instead of 5)."""
    scene, vis = many_lights
    ref = renderer(scene, vis, soft_shadows=False, num_random_dl=0).raw()[0]
    r = renderer(scene, vis, soft_shadows=False, num_random_dl=5)
    stack = r.raw_stack(N_FRAMES)
    n = len(r.prep.lights)
    biased = stack * ((n // 5) / (n / 5))  # every sample scaled by the truncated weight over the right one
    outliers, z_global, _ = _z_outliers(biased, ref)
    assert abs(z_global) > 10 and outliers > 0.1


def test03_soft_shadows_one_light_mean_equals_all_lights_mean(renderer, many_lights):
    """With soft shadows both estimators are random (area-light points); their means agree within the combined
    standard error."""
    scene, vis = many_lights
    all_stack = renderer(scene, vis, num_random_dl=0).raw_stack(48, first_seed=5000)
    one_stack = renderer(scene, vis, num_random_dl=1).raw_stack(N_FRAMES)
    outliers, _, _ = _z_outliers(one_stack, None, all_stack)
    assert outliers < 0.01
    rel = abs(one_stack.mean() - all_stack.mean()) / all_stack.mean()
    assert rel < 0.02


def _choices(n_lights, k, mode, power=None, points=20000):
    """The lights (and weights) the light-subsampling kernel picks for ``points`` points (one seed each) that read
    one row of ``n_lights`` lights of the given ``power``."""
    from methods.quake_drt.rng import pcg_np

    seeds = pcg_np(np.arange(points, dtype=np.uint32))
    power = np.ones(n_lights) if power is None else np.asarray(power, float)
    row_off = np.array([0, n_lights], np.int64)
    row_lights = np.arange(n_lights, dtype=np.int32)
    cdf = direct.row_power_cdf(row_off, row_lights, power)
    cap = points * max(k, 1)
    s_point, s_light, s_weight, s_dim = (np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap),
                                         np.empty(cap, np.int64))
    count, nxt, cand, sel = direct._select(0, np.zeros(points, np.int64), row_off, row_lights, cdf, k,
                                           direct.MODES.index(mode), seeds, np.empty(max(k, 1), np.int64), s_point,
                                           s_light, s_weight, s_dim)
    assert nxt == points and count == points * k and cand == points * n_lights and sel == points * k
    assert (s_point[:count] == np.repeat(np.arange(points), k)).all()
    return s_light[:count].reshape(points, k), s_weight[:count].reshape(points, k)


def test04_uniform_choice_covers_every_light_of_a_row_equally_first_and_last_included():
    """floor(u * n) with u < 1: no index past the row (the public code's round(u * n) reads one past the end and
    gives the first and last light half the probability)."""
    n, k, m = 7, 3, 20000
    chosen, _ = _choices(n, k, "uniform", points=m)
    assert chosen.min() >= 0 and chosen.max() < n
    assert all(len(set(row)) == k for row in chosen[:500])  # k distinct lights per point
    counts = np.bincount(chosen.reshape(-1), minlength=n)
    expected = m * k / n
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 30.0, counts  # chi-square, 6 degrees of freedom: p < 1e-4 above 27.9


def test05_power_choice_is_proportional_to_power_and_weighs_by_its_inverse():
    power = np.array([1.0, 2.0, 4.0, 1.0])
    m = 40000
    chosen, weight = _choices(4, 1, "power", power=power, points=m)
    counts = np.bincount(chosen[:, 0], minlength=4)
    p = power / power.sum()
    assert np.allclose(counts / m, p, atol=4 * np.sqrt(p * (1 - p) / m).max())
    assert np.allclose(weight[:, 0], 1.0 / p[chosen[:, 0]])  # weight 1 / (k p)
    _, w_uniform = _choices(7, 3, "uniform", points=10)
    assert np.all(w_uniform == 7 / 3)  # n / k as a float, not 7 // 3
