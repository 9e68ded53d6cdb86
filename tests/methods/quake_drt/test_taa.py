"""TAA (seed 001 §6.12): the history is clamped to the current 3x3 neighbourhood, fetched with Catmull-Rom,
blended with the new frame at weight 0.1, and a static image stays itself."""
import numpy as np
import pytest

from methods.quake_drt.taa import TAA


def test01_a_stale_history_is_clamped_into_the_current_neighbourhood():
    rng = np.random.default_rng(1)
    cur = (0.5 + 0.05 * rng.standard_normal((16, 16, 3))).astype(np.float32)
    taa = TAA(alpha=0.1, clamp_sigma=1.0, firefly_sigma=np.inf)
    taa.history = np.full((16, 16, 3), 5.0)  # a ghost: far brighter than anything in the frame
    out = taa(cur, np.zeros((16, 16, 2), np.float32))
    assert out.max() < 0.8  # without the clamp it would be 0.9 * 5 + 0.1 * 0.5 = 4.55
    # ... and lies between the neighbourhood's mean + sigma and the current colour, blended at 0.1.
    pad = np.pad(cur, ((1, 1), (1, 1), (0, 0)), mode="edge")
    win = np.stack([pad[1 + dy:17 + dy, 1 + dx:17 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    hi = win.mean(axis=0) + win.std(axis=0)
    inner = (slice(2, -2), slice(2, -2))
    assert np.allclose(out[inner], (0.9 * hi + 0.1 * cur)[inner], atol=1e-4)


def test02_a_wider_clamp_lets_more_history_through():
    cur = np.full((12, 12, 3), 0.5, np.float32)
    cur[::2, ::2] = 0.7
    hist = np.full((12, 12, 3), 2.0)
    outs = []
    for sigma in (1.0, 3.0):
        taa = TAA(clamp_sigma=sigma)
        taa.history = hist.copy()
        outs.append(taa(cur, np.zeros((12, 12, 2), np.float32)).mean())
    assert outs[1] > outs[0]


def test03_a_smooth_static_image_is_a_fixed_point_and_a_firefly_is_removed():
    yy, xx = np.mgrid[0:10, 0:14]
    img = np.stack([0.2 + 0.03 * xx, 0.3 + 0.02 * yy, 0.5 + 0.01 * (xx + yy)], axis=-1).astype(np.float32)
    taa = TAA()
    zero = np.zeros((10, 14, 2), np.float32)
    assert np.allclose(taa(img, zero), img, atol=1e-6)  # the first frame passes through
    for _ in range(5):
        out = taa(img, zero)
    assert np.allclose(out, img, atol=1e-5)
    spiky = img.copy()
    spiky[5, 7] = 50.0  # far outside 3 sigma of its neighbours: replaced by their mean
    assert TAA()(spiky, zero)[5, 7].max() < 1.0


@pytest.mark.parametrize("dx", [0.25, 0.5, 0.9])
def test04_the_history_is_fetched_with_catmull_rom_which_is_exact_on_ramps(dx):
    """History fetched half a pixel (or a quarter...) away: on a linear ramp Catmull-Rom interpolation is exact,
    so a history that is the same ramp moved by the motion vector gives back the current frame."""
    yy, xx = np.mgrid[0:12, 0:24].astype(np.float64)
    ramp = np.stack([0.02 * xx, 0.5 + 0.01 * yy, 0.3 + 0.01 * xx], axis=-1)
    taa = TAA(clamp_sigma=100.0, firefly_sigma=np.inf)
    taa.history = ramp.copy()
    moved = ramp + 0.02 * dx * np.array([1.0, 0.0, 0.5])  # the picture moved left by dx pixels
    motion = np.zeros((12, 24, 2), np.float32)
    motion[..., 0] = dx  # previous position = current + dx
    out = taa(moved.astype(np.float32), motion)
    assert np.allclose(out[3:-3, 3:-3], moved[3:-3, 3:-3], atol=1e-5)


@pytest.mark.parametrize("shift", [1, 3])
def test05_history_follows_the_motion_vectors(shift):
    """A picture moved right by ``shift`` pixels with motion vectors pointing back: the history is fetched where
    the pixel was, so a converged history reproduces the moved picture (no blur, no lag)."""
    rng = np.random.default_rng(4)
    base = rng.uniform(0.3, 0.7, (20, 30, 3))
    taa = TAA(clamp_sigma=10.0, firefly_sigma=np.inf)
    taa(base.astype(np.float32), np.zeros((20, 30, 2), np.float32))
    moved = np.roll(base, shift, axis=1)
    motion = np.zeros((20, 30, 2), np.float32)
    motion[..., 0] = -shift  # previous position = current - shift
    out = taa(moved.astype(np.float32), motion)
    inner = (slice(3, -3), slice(3 + shift, -3))
    assert np.allclose(out[inner], moved[inner], atol=1e-6)
