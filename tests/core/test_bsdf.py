"""suite.core.bsdf evaluates the material model exactly as Mitsuba 3's plugins do.

Mitsuba's ``BSDF::eval`` and ``BSDF::sample`` are called directly on random directions (llvm_ad_rgb, float32) and
compared with our float64 ports; agreement is at float32 precision (1e-5 relative), far below anything an image
comparison could resolve, so an error in a formula (a wrong Fresnel term, G1, D or roughplastic's tabulated
transmittance) shows up here first.
"""
import numpy as np
import pytest

from suite.core.bsdf import eval_bsdf, fresnel_conductor, fresnel_dielectric, reflect, refract
from suite.core.scene.model import Material


def mi():
    from suite.core.env import mitsuba

    return mitsuba("llvm")


def hemisphere(n, seed):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2]) + 1e-3
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def interaction(m, wi):
    si = m.SurfaceInteraction3f()
    si.wi = m.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    si.sh_frame = m.Frame3f(m.Vector3f(0, 0, 1))
    si.n = m.Normal3f(0, 0, 1)
    si.uv = m.Point2f(0.5, 0.5)
    return si


def rgb(values):
    return {"type": "rgb", "value": [float(x) for x in values]}


CASES = [
    ("diffuse", {"type": "diffuse", "reflectance": rgb([0.2, 0.5, 0.7])}, dict(albedo=[0.2, 0.5, 0.7])),
    ("roughconductor ggx", {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2},
     dict(kind="rough_conductor", distribution="ggx", roughness=0.2)),
    ("roughconductor beckmann eta k", {"type": "roughconductor", "alpha": 0.35, "eta": rgb([0.2, 0.9, 1.3]),
                                       "k": rgb([3.0, 2.5, 2.0]), "specular_reflectance": rgb([0.9, 0.8, 0.7])},
     dict(kind="rough_conductor", distribution="beckmann", roughness=0.35, conductor_eta=[0.2, 0.9, 1.3],
          conductor_k=[3.0, 2.5, 2.0], specular_reflectance=[0.9, 0.8, 0.7])),
    ("roughplastic ggx", {"type": "roughplastic", "distribution": "ggx", "alpha": 0.25,
                          "diffuse_reflectance": rgb([0.2, 0.5, 0.7])},
     dict(kind="rough_plastic", distribution="ggx", roughness=0.25, albedo=[0.2, 0.5, 0.7])),
    ("roughplastic beckmann nonlinear", {"type": "roughplastic", "alpha": 0.15, "int_ior": 1.6, "nonlinear": True,
                                         "diffuse_reflectance": rgb([0.8, 0.5, 0.1]),
                                         "specular_reflectance": rgb([0.9, 1.0, 0.8])},
     dict(kind="rough_plastic", distribution="beckmann", roughness=0.15, int_ior=1.6, ext_ior=1.000277,
          nonlinear=True, albedo=[0.8, 0.5, 0.1], specular_reflectance=[0.9, 1.0, 0.8])),
]


@pytest.mark.parametrize("name, plugin, params", CASES, ids=[c[0] for c in CASES])
def test01_eval_matches_mitsuba(name, plugin, params):
    m = mi()
    n = 4000
    wi, wo = hemisphere(n, 1), hemisphere(n, 2)
    wo[: n // 4, 2] *= -1  # some directions below the surface: both must give zero
    ref = np.array(m.load_dict(plugin).eval(m.BSDFContext(), interaction(m, wi), m.Vector3f(*wo.T)))
    ref = ref.T if ref.shape[0] == 3 else ref
    mat = Material("m", **{"albedo": [0.0] * 3, **params})
    ours = eval_bsdf(mat, wi, wo, np.tile([0.0, 0.0, 1.0], (n, 1)), np.tile(mat.albedo, (n, 1)))
    np.testing.assert_allclose(ours, ref, rtol=2e-4, atol=2e-5 * np.abs(ref).max())
    assert np.all(ours[: n // 4] == 0)


def test02_a_wrong_roughness_or_distribution_is_far_outside_that_precision():
    m = mi()
    wi, wo = hemisphere(2000, 3), hemisphere(2000, 4)
    ref = np.array(m.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": 0.2})
                   .eval(m.BSDFContext(), interaction(m, wi), m.Vector3f(*wo.T))).T
    nrm = np.tile([0.0, 0.0, 1.0], (len(wi), 1))
    for wrong in (dict(roughness=0.22, distribution="ggx"), dict(roughness=0.2, distribution="beckmann")):
        ours = eval_bsdf(Material("m", [0] * 3, kind="rough_conductor", **wrong), wi, wo, nrm, np.zeros((len(wi), 3)))
        assert np.abs(ours - ref).max() > 100 * 2e-5 * np.abs(ref).max()


@pytest.mark.parametrize("eta", [1.5, 1.0 / 1.33])
def test03_dielectric_fresnel_and_radiance_scaling_match_mitsuba_sampling(eta):
    """Mitsuba's dielectric picks reflection with probability F (its pdf) and scales refracted radiance by eta_ti^2."""
    m = mi()
    n = 3000
    wi = hemisphere(n, 5)
    wi[n // 2:, 2] *= -1  # half of the rays arrive from inside
    bsdf = m.load_dict({"type": "dielectric", "int_ior": eta, "ext_ior": 1.0})
    si = interaction(m, wi)
    f, cos_t, _, eta_ti = fresnel_dielectric(wi[:, 2], eta)
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    for u, branch in ((0.0, "reflect"), (0.999999, "refract")):
        bs, weight = bsdf.sample(m.BSDFContext(), si, m.Float(np.full(n, u)), m.Point2f(0.5, 0.5))
        pdf, wo, weight = np.array(bs.pdf), np.array(bs.wo).reshape(3, -1).T, np.array(weight).reshape(3, -1).T
        if branch == "reflect":
            np.testing.assert_allclose(pdf, f, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(wo, reflect(wi, nrm), atol=2e-6)
            np.testing.assert_allclose(weight[:, 0], 1.0, rtol=1e-6)
        else:
            ok = f < 1 - 1e-6  # total internal reflection has no refracted branch
            np.testing.assert_allclose(pdf[ok], 1 - f[ok], rtol=1e-4, atol=1e-6)
            np.testing.assert_allclose(wo[ok], refract(wi, nrm, cos_t, eta_ti)[ok], atol=5e-6)
            np.testing.assert_allclose(weight[ok, 0], (eta_ti ** 2)[ok], rtol=1e-5)
    assert (f[n // 2:] == 1).any() == (eta > 1)  # total internal reflection from inside the denser medium


def test04_conductor_fresnel_matches_mitsuba_and_defaults_to_a_perfect_mirror():
    m = mi()
    wi = hemisphere(2000, 6)
    bsdf = m.load_dict({"type": "conductor", "eta": rgb([0.2, 0.9, 1.3]), "k": rgb([3.0, 2.5, 2.0])})
    _, weight = bsdf.sample(m.BSDFContext(), interaction(m, wi), m.Float(np.zeros(len(wi))), m.Point2f(0.5, 0.5))
    ours = fresnel_conductor(wi[:, 2:3], np.array([0.2, 0.9, 1.3]), np.array([3.0, 2.5, 2.0]))
    np.testing.assert_allclose(ours, np.array(weight).reshape(3, -1).T, rtol=1e-5)
    np.testing.assert_array_equal(fresnel_conductor(wi[:, 2:3], np.zeros(3), np.ones(3)), 1.0)
