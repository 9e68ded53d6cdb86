"""The layered SVGF (§4.4.1) as a Dr.Jit kernel (methods/layered_pvs/device.py): the numba kernel's values, to
rounding, on every Dr.Jit variant (llvm_ad_rgb here, cuda_ad_rgb where a GPU is usable), and the server's denoise
stage takes it on such a tracer."""
from types import SimpleNamespace

import numpy as np
import pytest

from methods.layered_pvs import server as sv
from methods.layered_pvs.device import svgf_passes
from suite.core.trace import backend_params

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")
def _layers(seed, L=3, H=13, W=17):
    """Two or three surfaces per pixel a little apart, holes, slanted and turned normals (some facing away)."""
    rng = np.random.default_rng(seed)
    valid = np.zeros((L, H, W), bool)
    valid[0] = rng.random((H, W)) < 0.9
    for k in range(1, L):
        valid[k] = valid[k - 1] & (rng.random((H, W)) < 0.6)
    depth = np.where(valid, 2.0 + np.arange(L)[:, None, None] * 0.3 + rng.random((L, H, W)) * 0.05, 0.0)
    yy, xx = np.mgrid[0:H, 0:W]
    position = np.stack([xx * 0.02, yy * 0.02, np.zeros((H, W))], -1)[None] + \
        np.stack([np.zeros_like(depth), np.zeros_like(depth), depth], -1)
    normal = np.zeros((L, H, W, 3))
    normal[..., 2] = -1.0
    normal[..., 0] = rng.normal(0, 0.3, (L, H, W))
    normal[-1, ::3, ::2, 2] = 1.0
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    illum = np.where(valid[..., None], rng.random((L, H, W, 3)) * 2.0, 0.0)
    variance = np.where(valid, rng.random((L, H, W)) * 0.2, 0.0)
    return illum, variance, position, normal, valid, depth


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("sigma_n, iterations, layers", [(128.0, 3, 3), (12.5, 2, 2), (3.0, 5, 1)])
def test01_the_device_passes_give_the_numba_kernels_values(drjit_device, backend, sigma_n, iterations, layers,
                                                           at_parity):
    # 5 passes reach step 16, wider than the 17x13 grid: taps leave it
    illum, variance, position, normal, valid, depth = _layers(int(sigma_n), L=layers)
    illum = illum + np.where(valid[..., None], 0.0, 7.0)     # slots without a fragment come out 0 whatever they hold
    if layers == 3:  # fragments behind empty layers: a tap's search stops at the first empty layer
        valid[:, 0, :] = [[False], [False], [True]]
        position[2, 0], normal[2, 0], depth[2, 0] = position[0, 1], normal[0, 1], depth[0, 1]
        illum[2, 0] = illum[0, 1] + 0.5
    pix_angle = 2 * np.tan(np.radians(30.0)) / valid.shape[2]
    grids = [sv.pixel_major(a, np.float64) for a in (illum, variance, position, normal)] + \
        [sv.pixel_major(valid, np.bool_), sv.pixel_major(depth, np.float64)]
    want = sv._svgf_passes(*grids, pix_angle, iterations, sigma_n=sigma_n)
    got = svgf_passes(drjit_device(backend), *grids, pix_angle, iterations, sigma_n=sigma_n)
    assert got.shape == want.shape and got.dtype == np.float64
    if backend == "mitsuba-llvm":
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    else:  # cuda's fused multiply-adds can tip a tap's choice between two nearly equidistant fragments
        at_parity(got, want, share=0.999, rtol=1e-9, atol=1e-12)
    v = sv.pixel_major(valid, np.bool_)
    assert (got[~v] == 0).all() and not np.allclose(got[v], grids[0][v], rtol=1e-3)


@pytest.mark.parametrize("backend", DRJIT)
def test02_denoise_fragments_on_a_device_counts_its_copies(drjit_device, backend):
    illum_g, _, position, normal, valid, depth = _layers(8, L=2)
    index = np.nonzero(valid)
    n = len(index[0])
    rng = np.random.default_rng(1)
    frag = SimpleNamespace(index=index, position=position[index], normal=normal[index])
    layers = SimpleNamespace(prim=np.zeros(valid.shape, np.int64), valid=valid, t=np.where(valid, depth, np.inf))
    view = SimpleNamespace(fov_deg=60.0, width=valid.shape[2])
    illum, m1 = illum_g[index], rng.random(n)
    m2 = m1 * m1 + rng.random(n) * 0.1
    dev = drjit_device(backend)
    want = sv.denoise_fragments(view, layers, frag, illum, m1, m2, spp=2, iterations=3)
    before = dev.counters["bytes_to_host"]
    got = sv.denoise_fragments(view, layers, frag, illum, m1, m2, spp=2, iterations=3, device=dev)
    assert dev.counters["bytes_to_host"] - before == valid.size * 3 * 8      # the filtered grid, once
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)              # both rounded to float32
