"""A-SVGF (seed 001 Table 6.9): a paused static scene converges to the accumulated ground truth; gradient
samples re-shade the previous frame's points with its seeds, so a static scene has no gradient at all; a light
switched off is picked up by the gradient in the frame it happens instead of ghosting for many frames (as it does
with plain SVGF accumulation); and the filter stages work on their own."""
import numpy as np
import pytest

from methods.quake_drt import asvgf
from methods.quake_drt.testscenes import switch_off
from suite.core.metrics import compare

T_OFF = 10  # the frame at which the light goes off


def _switch_off(scene, name, frame=T_OFF):
    """Makes ``scene.lights_at`` return light ``name`` with zero intensity from ``frame`` on."""
    switch_off(scene, name, frame)


def _run(r, frames):
    """Full frames with scene time advancing (the camera path of the test scenes holds still)."""
    return r.run(frames)


@pytest.fixture
def room(two_rooms):
    return two_rooms(door_open=False, lights_in_b=1, camera="a", resolution=(64, 40))


def test01_a_paused_static_scene_converges_to_the_accumulated_ground_truth(renderer, room):
    scene, vis = room
    gt = renderer(scene, vis, (64, 40), num_random_dl=0).raw_stack(16).mean(axis=0)
    r = renderer(scene, vis, (64, 40), num_random_dl=1, denoiser=True, taa=True)
    frames = _run(r, 24)
    final, denoised = frames[-1][0], frames[-1][1]
    raw_img = frames[-1][2].compose()
    ssim_raw = compare(gt, raw_img)["ssim"]
    ssim_denoised, ssim_final = compare(gt, denoised)["ssim"], compare(gt, final)["ssim"]
    # (TAA's exponential history still holds some of the first, less converged frames after 24 of them.)
    assert ssim_denoised > 0.93 and ssim_final > 0.9 and ssim_final > ssim_raw + 0.5, (ssim_denoised, ssim_final,
                                                                                       ssim_raw)
    assert abs(final.mean() - gt.mean()) / gt.mean() < 0.03
    assert frames[-1][3]["hist_len_max"] == 24


def test02_a_static_scene_has_no_gradient(renderer, room):
    """Each gradient sample shades the previous frame's surface point with the previous frame's seed, so the
    same random numbers: in a static scene the difference is zero up to the rounding of the re-computed point,
    however noisy one light per pixel is."""
    scene, vis = room
    r = renderer(scene, vis, (64, 40), num_random_dl=1, denoiser=True)
    frames = _run(r, 4)
    assert all(rec["gradient_samples"] > 0.8 * (64 // 3) * (40 // 3) for *_, rec in frames[1:])
    assert all(rec["antilag_mean"] < 1e-5 for *_, rec in frames)


@pytest.mark.parametrize("antilag", [True, False])
def test03_a_light_switched_off_is_picked_up_by_the_gradient_instead_of_ghosting(renderer, room, antilag):
    scene, vis = room
    gt_on = renderer(scene, vis, (64, 40), num_random_dl=0).raw_stack(8).mean(axis=0)
    off = renderer(scene, vis, (64, 40), num_random_dl=0)
    _switch_off(off.scene, "a_ceiling")
    gt_off = np.stack([off.raw(50 + i, t_s=1.0)[0] for i in range(8)]).mean(axis=0)
    step = np.abs(gt_on - gt_off).mean(axis=-1)
    region = step > 0.2 * step.max()  # where the switched-off light mattered
    r = renderer(scene, vis, (64, 40), num_random_dl=1, denoiser=True, taa=False, asvgf_antilag=antilag)
    _switch_off(r.scene, "a_ceiling")
    frames = _run(r, T_OFF + 4)
    # Residual of the switched-off light, as a fraction of the step, in the frames after the switch.
    residual = [np.abs(img - gt_off).mean(axis=-1)[region].mean() / step[region].mean() for img, *_ in frames]
    assert residual[T_OFF - 1] > 0.9  # still on
    if antilag:
        assert frames[T_OFF][3]["antilag_mean"] > 0.2
        assert max(residual[T_OFF:T_OFF + 3]) < 0.2, residual[T_OFF:]
    else:
        assert min(residual[T_OFF:T_OFF + 3]) > 0.5, residual[T_OFF:]  # ghosting


def test04_gradient_atrous_spreads_a_sparse_gradient_and_normalises_it():
    den = asvgf.ASVGF(asvgf.ASVGFSettings(), 30, 30)
    grad = np.zeros((10, 10, 4), np.float32)
    grad[..., 2], grad[..., 3] = 1.0, 0.1
    grad[4, 4, :2] = (-0.5, 0.5)  # one cell lost half its light
    lam = den.gradient_atrous(grad)
    assert lam[4, 4] == pytest.approx(1.0) and lam[4, 6] > 0.5  # |delta| / max after the same spreading
    assert lam[0, 0] == pytest.approx(1.0)  # the ratio, not the magnitude, is what spreads
    assert (lam >= 0).all() and (lam <= 1).all()
    assert den.gradient_atrous(np.zeros((10, 10, 4), np.float32)).max() == 0.0  # nothing lit: no gradient


def test05_atrous_keeps_edges_and_removes_noise():
    """Two flat regions with different normals and noise: the filter removes most of the noise without mixing
    the regions."""
    h, w = 32, 32
    rng = np.random.default_rng(0)
    normal = np.zeros((h, w, 3), np.float32)
    normal[:, :16, 2], normal[:, 16:, 0] = 1.0, 1.0
    truth = np.where(np.arange(w)[None, :, None] < 16, 1.0, 0.2) * np.ones((h, w, 3))
    noisy = (truth * rng.uniform(0.5, 1.5, (h, w, 1))).astype(np.float32)
    g = asvgf.Guides(valid=np.ones((h, w), bool), point=np.zeros((h, w, 3)), depth=np.ones((h, w)),
                     normal=normal, motion=np.zeros((h, w, 2), np.float32), filter_depth=np.ones((h, w)),
                     filter_normal=normal, camera=np.zeros(3))
    den = asvgf.ASVGF(asvgf.ASVGFSettings(), w, h)
    var = den.variance(noisy, np.zeros((h, w, 2), np.float32), np.ones((h, w), np.float32), g)
    out, _ = den.atrous(noisy, var, g)
    err_in, err_out = np.abs(noisy - truth)[:, 2:14].mean(), np.abs(out - truth)[:, 2:14].mean()
    assert err_out < 0.35 * err_in
    assert np.abs(out[:, 16:] - 0.2).mean() < 0.05  # the dark side did not take light from the bright side
