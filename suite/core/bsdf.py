"""BSDFs of the material model, numpy ports of Mitsuba 3's plugins (so that references agree exactly).

Sources, Mitsuba 3 (``include/mitsuba/render/fresnel.h``, ``microfacet.h``, ``src/bsdfs/*.cpp``):

* ``fresnel_dielectric``: ``fresnel()``: unpolarised Fresnel reflectance with the transmitted cosine and the
  relative IORs along the direction of travel; exactly 1 at grazing incidence and 0 when index-matched.
* ``fresnel_conductor``: ``fresnel_conductor()`` (Moeller, "Optics"); eta = 0, k = 1 gives exactly 1.
* :class:`Microfacet`: ``MicrofacetDistribution`` for an isotropic ``alpha`` (clamped at 1e-4 like Mitsuba):
  ``eval`` (D), ``smith_g1`` (Beckmann through Mitsuba's rational approximation, GGX exact) and visible-normal
  sampling (used only to tabulate ``roughplastic``'s transmittance, as Mitsuba does).
* ``eval_reflectance`` / ``eval_transmittance``: the Gauss-Legendre tables of ``roughplastic``.
* :func:`eval_bsdf`: ``BSDF::eval`` of diffuse, roughconductor and roughplastic, i.e. the BSDF times the
  cosine of the outgoing direction, ``f(wi, wo) * cos(theta_o)``, zero unless both directions are above the
  surface. The caller orients ``n`` (two-sided materials flip it toward ``wi``).

Directions are world-space unit vectors, (N, 3) float64; ``wi`` points toward the viewer, ``wo`` toward the
light (Mitsuba's convention in ``eval``).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

INV_PI = 1.0 / np.pi
INV_SQRT_PI = 1.0 / np.sqrt(np.pi)
# Resolution of roughplastic's transmittance table (MI_ROUGH_TRANSMITTANCE_RES).
ROUGH_TRANSMITTANCE_RES = 64


def _dot(a, b):
    return np.einsum("...k,...k->...", a, b)


def _normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def fresnel_dielectric(cos_theta_i, eta):
    """Mitsuba's ``fresnel(cos_theta_i, eta)`` -> (F, cos_theta_t, eta_it, eta_ti). ``cos_theta_i`` < 0 means
    the ray arrives from inside (the side the normal does not point to); ``cos_theta_t`` has the opposite sign."""
    cos_theta_i = np.asarray(cos_theta_i, np.float64)
    eta = np.float64(eta)
    outside = cos_theta_i >= 0.0
    eta_it = np.where(outside, eta, 1.0 / eta)
    eta_ti = np.where(outside, 1.0 / eta, eta)
    cos_theta_t_sqr = 1.0 - (1.0 - cos_theta_i * cos_theta_i) * (eta_ti * eta_ti)
    cos_i_abs = np.abs(cos_theta_i)
    cos_t_abs = np.sqrt(np.maximum(cos_theta_t_sqr, 0.0))
    index_matched = eta == 1.0
    special = index_matched | (cos_i_abs == 0.0)
    a_s = (cos_i_abs - eta_it * cos_t_abs) / (cos_i_abs + eta_it * cos_t_abs)
    a_p = (cos_t_abs - eta_it * cos_i_abs) / (cos_t_abs + eta_it * cos_i_abs)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = 0.5 * (a_s * a_s + a_p * a_p)
    r = np.where(special, 0.0 if index_matched else 1.0, r)
    cos_theta_t = np.where(cos_theta_i >= 0.0, -cos_t_abs, cos_t_abs)  # mulsign_neg
    return r, cos_theta_t, eta_it, eta_ti


def fresnel_conductor(cos_theta_i, eta_r, eta_i):
    """Mitsuba's ``fresnel_conductor``: unpolarised reflectance of a conductor with complex IOR eta_r + i eta_i.
    Broadcasts (e.g. cos (N, 1) against RGB (3,))."""
    c2 = cos_theta_i * cos_theta_i
    s2 = 1.0 - c2
    s4 = s2 * s2
    temp_1 = eta_r * eta_r - eta_i * eta_i - s2
    a_2_pb_2 = np.sqrt(np.maximum(temp_1 * temp_1 + 4.0 * eta_i * eta_i * eta_r * eta_r, 0.0))
    a = np.sqrt(np.maximum(0.5 * (a_2_pb_2 + temp_1), 0.0))
    term_1 = a_2_pb_2 + c2
    term_2 = 2.0 * cos_theta_i * a
    r_s = (term_1 - term_2) / (term_1 + term_2)
    term_3 = a_2_pb_2 * c2 + s4
    term_4 = term_2 * s2
    r_p = r_s * (term_3 - term_4) / (term_3 + term_4)
    return 0.5 * (r_s + r_p)


def reflect(wi, n):
    """Mirror ``wi`` (pointing away from the surface) about ``n``: ``2 (wi.n) n - wi``."""
    return 2.0 * _dot(wi, n)[..., None] * n - wi


def refract(wi, n, cos_theta_t, eta_ti):
    """Mitsuba's ``refract(wi, m, cos_theta_t, eta_ti)`` (``cos_theta_t``, ``eta_ti`` from fresnel_dielectric)."""
    return n * (_dot(wi, n) * eta_ti + cos_theta_t)[..., None] - wi * np.asarray(eta_ti)[..., None]


class Microfacet:
    """Mitsuba's isotropic ``MicrofacetDistribution`` (``beckmann`` or ``ggx``) in a local frame (z = normal)."""

    def __init__(self, distribution: str, alpha: float):
        self.ggx = distribution == "ggx"
        self.alpha = max(float(alpha), 1e-4)

    def eval(self, cos_m):
        """D(m) from the cosine of the microfacet normal (unit vectors: x^2 + y^2 = 1 - cos^2)."""
        a2 = self.alpha * self.alpha
        c2 = cos_m * cos_m
        xy2 = np.maximum(1.0 - c2, 0.0)
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            if self.ggx:
                result = 1.0 / (np.pi * a2 * np.square(xy2 / a2 + c2))
            else:
                result = np.exp(-(xy2 / a2) / c2) / (np.pi * a2 * c2 * c2)
        result = np.where(np.isfinite(result), result, 0.0)
        return np.where(result * cos_m > 1e-20, result, 0.0)

    def smith_g1(self, cos_v, v_dot_m):
        """G1(v, m) from cos(theta_v) and v.m."""
        xy_alpha_2 = self.alpha * self.alpha * np.maximum(1.0 - cos_v * cos_v, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tan_theta_alpha_2 = xy_alpha_2 / (cos_v * cos_v)
            if self.ggx:
                result = 2.0 / (1.0 + np.sqrt(1.0 + tan_theta_alpha_2))
            else:
                a = 1.0 / np.sqrt(tan_theta_alpha_2)
                a_sqr = a * a
                result = np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a_sqr) / (1.0 + 2.276 * a + 2.577 * a_sqr))
        result = np.where(xy_alpha_2 == 0.0, 1.0, result)
        return np.where(v_dot_m * cos_v <= 0.0, 0.0, result)

    def _sample_visible_11(self, cos_theta_i, u):
        if self.ggx:
            # warp::square_to_uniform_disk_concentric
            x, y = 2.0 * u[..., 0] - 1.0, 2.0 * u[..., 1] - 1.0
            q13 = np.abs(x) < np.abs(y)
            r = np.where(q13, y, x)
            rp = np.where(q13, x, y)
            with np.errstate(divide="ignore", invalid="ignore"):
                phi = 0.25 * np.pi * rp / r
            phi = np.where(q13, 0.5 * np.pi - phi, phi)
            phi = np.where((x == 0) & (y == 0), 0.0, phi)
            px, py = r * np.cos(phi), r * np.sin(phi)
            s = 0.5 * (1.0 + cos_theta_i)
            a = np.sqrt(np.maximum(1.0 - px * px, 0.0))
            py = a * (1.0 - s) + py * s
            z = np.sqrt(np.maximum(1.0 - px * px - py * py, 0.0))
            sin_theta_i = np.sqrt(np.maximum(1.0 - cos_theta_i * cos_theta_i, 0.0))
            norm = 1.0 / (sin_theta_i * py + cos_theta_i * z)
            return np.stack([(cos_theta_i * py - sin_theta_i * z) * norm, px * norm], axis=-1)
        from scipy.special import erf, erfinv

        tan_theta_i = np.sqrt(np.maximum(1.0 - cos_theta_i * cos_theta_i, 0.0)) / cos_theta_i
        with np.errstate(divide="ignore"):
            cot_theta_i = 1.0 / tan_theta_i
        maxval = erf(cot_theta_i)
        u = np.clip(u, 1e-6, 1.0 - 1e-6)
        x = maxval - (maxval + 1.0) * erf(np.sqrt(-np.log(u[..., 0])))
        sx = u[..., 0] * (1.0 + maxval + INV_SQRT_PI * tan_theta_i * np.exp(-cot_theta_i * cot_theta_i))
        for _ in range(3):
            slope = erfinv(x)
            value = 1.0 + x + INV_SQRT_PI * tan_theta_i * np.exp(-slope * slope) - sx
            derivative = 1.0 - slope * tan_theta_i
            x = x - value / derivative
        return np.stack([erfinv(x), erfinv(2.0 * u[..., 1] - 1.0)], axis=-1)

    def sample_visible(self, wi, u):
        """Visible-normal sample (Heitz & d'Eon) for local ``wi`` (..., 3) and uniform ``u`` (..., 2)."""
        a = self.alpha
        wi_p = _normalize(np.stack([a * wi[..., 0], a * wi[..., 1], wi[..., 2]], axis=-1))
        sin_theta_2 = wi_p[..., 0] ** 2 + wi_p[..., 1] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.sqrt(sin_theta_2)
            degenerate = np.abs(sin_theta_2) <= 4.0 * 2.0 ** -24  # Frame::sincos_phi
            cos_phi = np.where(degenerate, 1.0, np.clip(wi_p[..., 0] * inv, -1.0, 1.0))
            sin_phi = np.where(degenerate, 0.0, np.clip(wi_p[..., 1] * inv, -1.0, 1.0))
        slope = self._sample_visible_11(wi_p[..., 2], u)
        sx = (cos_phi * slope[..., 0] - sin_phi * slope[..., 1]) * a
        sy = (sin_phi * slope[..., 0] + cos_phi * slope[..., 1]) * a
        return _normalize(np.stack([-sx, -sy, np.ones_like(sx)], axis=-1))


def _quadrature(distr: Microfacet, wi, eta: float, transmit: bool):
    """Mitsuba's ``eval_reflectance`` / ``eval_transmittance``: Gauss-Legendre over visible normals."""
    res = 32 if eta > 1 else 128
    nodes, weights = np.polynomial.legendre.leggauss(res)
    nx, ny = np.meshgrid(nodes, nodes, indexing="xy")
    wx, wy = np.meshgrid(weights, weights, indexing="xy")
    u = np.stack([nx.ravel(), ny.ravel()], -1) * 0.5 + 0.5
    w = (wx * wy).ravel() * 0.25
    wi_b = np.broadcast_to(wi[:, None, :], (len(wi), len(u), 3))
    m = distr.sample_visible(wi_b, np.broadcast_to(u[None], (len(wi), len(u), 2)))
    wi_m = _dot(wi_b, m)
    f, cos_theta_t, _, eta_ti = fresnel_dielectric(wi_m, eta)
    if transmit:
        wo = refract(wi_b, m, cos_theta_t, eta_ti)
        smith = distr.smith_g1(wo[..., 2], _dot(wo, m)) * (1.0 - f)
        smith = np.where(wo[..., 2] * wi_b[..., 2] >= 0.0, 0.0, smith)
    else:
        wo = reflect(wi_b, m)
        smith = distr.smith_g1(wo[..., 2], _dot(wo, m)) * f
        smith = np.where((wo[..., 2] <= 0.0) | (wi_b[..., 2] <= 0.0), 0.0, smith)
    return (smith * w).sum(axis=1)


@lru_cache(maxsize=64)
def rough_plastic_tables(distribution: str, alpha: float, eta: float) -> tuple[np.ndarray, float]:
    """roughplastic's precomputation: (external transmittance at cos = 0..1 in 64 steps, internal reflectance)."""
    alpha, eta = float(np.float32(alpha)), float(np.float32(eta))  # Mitsuba tabulates in float32 scalars
    distr = Microfacet(distribution, alpha)
    mu = np.maximum(1e-6, np.linspace(0.0, 1.0, ROUGH_TRANSMITTANCE_RES))
    wi = np.stack([np.sqrt(1.0 - mu * mu), np.zeros_like(mu), mu], axis=-1)
    external = _quadrature(distr, wi, eta, transmit=True)
    internal = float(np.mean(_quadrature(distr, wi, 1.0 / eta, transmit=False) * wi[:, 2]) * 2.0)
    return external, internal


def _lerp_gather(table, x):
    size = len(table)
    x = np.asarray(x, np.float64) * (size - 1)
    index = np.minimum(np.maximum(x, 0.0).astype(np.int64), size - 2)
    w1 = x - index
    return (1.0 - w1) * table[index] + w1 * table[index + 1]


def eval_bsdf(material, wi, wo, n, albedo):
    """``BSDF::eval`` (f * cos theta_o) of ``material`` for (N, 3) directions around oriented normals ``n``.

    ``albedo`` (N, 3) is the diffuse reflectance at the points (textures already looked up). Delta BSDFs
    (mirror, glass) have no density to evaluate: zero.
    """
    kind = material.shading_kind
    cos_i, cos_o = _dot(wi, n), _dot(wo, n)
    active = (cos_i > 0.0) & (cos_o > 0.0)
    out = np.zeros((len(cos_i), 3), np.float64)
    if kind == "diffuse":
        out = np.asarray(albedo, np.float64) * (INV_PI * np.where(active, cos_o, 0.0))[:, None]
        return out
    if kind not in ("rough_conductor", "rough_plastic"):
        return out
    distr = Microfacet(material.distribution, material.roughness)
    h = _normalize(wi + wo)
    cos_h = _dot(h, n)
    d = distr.eval(cos_h)
    wi_h, wo_h = _dot(wi, h), _dot(wo, h)
    g = distr.smith_g1(cos_i, wi_h) * distr.smith_g1(cos_o, wo_h)
    safe_cos_i = np.where(active, cos_i, 1.0)
    spec = np.asarray(material.specular_reflectance, np.float64)
    if kind == "rough_conductor":
        active = active & (d != 0.0)
        value = (d * g / (4.0 * safe_cos_i))[:, None]
        f = fresnel_conductor(wi_h[:, None], np.asarray(material.conductor_eta, np.float64),
                              np.asarray(material.conductor_k, np.float64))
        out = f * value * spec
    else:
        eta = material.eta
        f = fresnel_dielectric(wi_h, eta)[0]
        out = (f * d * g / (4.0 * safe_cos_i))[:, None] * spec
        external, internal = rough_plastic_tables(material.distribution, material.roughness, eta)
        t_i, t_o = _lerp_gather(external, cos_i), _lerp_gather(external, cos_o)
        diff = np.asarray(albedo, np.float64)
        diff = diff / (1.0 - (diff * internal if material.nonlinear else internal))
        out = out + diff * (INV_PI / (eta * eta) * cos_o * t_i * t_o)[:, None]
    return np.where(active[:, None], out, 0.0)
