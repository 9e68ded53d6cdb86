"""Alpha testing: hits on transparent texels of alpha-tested materials do not count.

A material with an ``opacity_texture`` exists only where its bilinearly filtered opacity at the hit's UV is at
least its ``alpha_threshold`` (0.5 by default, Quake III's ``alphaFunc GE128``). Neither backend can skip a
hit inside its traversal here (embreex exposes no intersection filter, and a Mitsuba ``mask`` is stochastic), so
the tracer resolves alpha after the backend query: a ray whose closest hit is transparent is traced again from
just past that hit, until it finds an opaque hit, leaves its [tmin, tmax) interval, or has crossed
``MAX_ALPHA_LAYERS`` transparent hits. Every re-traced ray is a real backend query and counts in
``rays_intersect``.

Mitsuba's own ``mask`` BSDF keeps a surface with probability = opacity; for binary opacity maps both models
agree (up to the bilinear ramp one texel wide at the map's edges).
"""
from __future__ import annotations

import numpy as np

from suite.core.trace.robust import FLOAT_SCALE

# A ray crossing more transparent hits than this keeps the last one as its hit (or counts as occluded): a
# guard against pathological stacks of coplanar alpha-tested faces, far above any real scene's depth complexity.
MAX_ALPHA_LAYERS = 64
# Re-traced rays start this many float32 ULPs (of the hit's largest coordinate in the tracing frame, or of its
# distance, whichever is larger) past the transparent hit. Surfaces closer than that behind it are skipped too.
ALPHA_STEP_ULPS = 16.0


def _transparent(prim, u, v, faces, uvs, face_material, mid, texture, threshold, out):
    """``out[i] = True`` where hit i lies on a face of material ``mid`` whose bilinear opacity (``texture`` (H, W, 1),
    :func:`suite.core.gbuffer.lookup_texture`'s conventions) is below ``threshold``: :meth:`AlphaTest.opacity` and
    the comparison of :meth:`AlphaTest.transparent` per hit, in their float64 order."""
    h, w = texture.shape[0], texture.shape[1]
    for i in range(len(prim)):
        p = prim[i]
        if p < 0 or face_material[p] != mid:
            continue
        b1, b2 = np.float64(u[i]), np.float64(v[i])
        b0 = (1.0 - b1) - b2
        f0, f1, f2 = faces[p, 0], faces[p, 1], faces[p, 2]
        uvx = (np.float64(uvs[f0, 0]) * b0 + np.float64(uvs[f1, 0]) * b1) + np.float64(uvs[f2, 0]) * b2
        uvy = (np.float64(uvs[f0, 1]) * b0 + np.float64(uvs[f1, 1]) * b1) + np.float64(uvs[f2, 1]) * b2
        x = uvx * w - 0.5
        y = uvy * h - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        x0i, y0i = np.int64(x0) % w, np.int64(y0) % h
        x1i, y1i = (x0i + 1) % w, (y0i + 1) % h
        val = (((1 - fx) * (1 - fy) * np.float64(texture[y0i, x0i, 0]) + fx * (1 - fy) * np.float64(texture[y0i, x1i, 0]))
               + (1 - fx) * fy * np.float64(texture[y1i, x0i, 0])) + fx * fy * np.float64(texture[y1i, x1i, 0])
        out[i] = np.float32(val) < threshold


_transparent_kernel = None


class AlphaTest:
    """Per-face opacity lookup for the alpha-tested materials of a scene."""

    def __init__(self, scene):
        from suite.core.gbuffer import lookup_texture

        self._lookup = lookup_texture
        self.faces = scene.faces
        self.uvs = scene.uvs
        self.face_material = scene.face_material
        self.textures = {i: m.opacity_texture for i, m in enumerate(scene.materials) if m.is_alpha_tested}
        self.threshold = np.array([m.alpha_threshold if m.is_alpha_tested else 0.0 for m in scene.materials],
                                  np.float32)
        tested = np.zeros(len(scene.materials), bool)
        tested[list(self.textures)] = True
        self.face_tested = tested[scene.face_material]

    @classmethod
    def for_scene(cls, scene):
        """An AlphaTest, or None when no material is alpha-tested (then tracers do nothing extra)."""
        return cls(scene) if any(m.is_alpha_tested for m in scene.materials) else None

    def _tested(self, prim: np.ndarray) -> np.ndarray:
        """Indices of the hits that lie on alpha-tested faces."""
        prim = np.asarray(prim)
        tested = np.zeros(len(prim), bool)
        hit = prim >= 0
        tested[hit] = self.face_tested[prim[hit]]
        return np.nonzero(tested)[0]

    def opacity(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N,) float32 filtered opacity at the hits (1 on faces without an opacity map, 0 for misses)."""
        prim = np.asarray(prim)
        out = np.where(prim >= 0, 1.0, 0.0).astype(np.float32)
        idx = self._tested(prim)
        if len(idx) == 0:
            return out
        p = prim[idx]
        w = np.stack([1.0 - u[idx].astype(np.float64) - v[idx], u[idx], v[idx]], axis=-1)[..., None]
        uv = (self.uvs[self.faces[p]].astype(np.float64) * w).sum(axis=1)  # interpolated texture coordinates
        mat = self.face_material[p]
        for mid, tex in self.textures.items():
            sel = mat == mid
            if sel.any():
                out[idx[sel]] = self._lookup(tex, uv[sel])[:, 0]
        return out

    def transparent(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N,) bool: the hit lies where its material's opacity is below its threshold (misses are not). One compiled
        pass over the hits per alpha-tested material (the bits of :meth:`transparent_reference`)."""
        global _transparent_kernel
        if _transparent_kernel is None:
            import numba

            _transparent_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_transparent)
        prim = np.ascontiguousarray(prim, np.int32)
        u, v = (np.ascontiguousarray(x, x.dtype if x.dtype in (np.float32, np.float64) else np.float64)
                for x in (np.asarray(u), np.asarray(v)))
        out = np.zeros(len(prim), bool)
        for mid, tex in self.textures.items():
            _transparent_kernel(prim, u, v, self.faces, self.uvs, self.face_material, mid,
                                np.ascontiguousarray(tex, np.float32), self.threshold[mid], out)
        return out

    def transparent_reference(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """:meth:`transparent` as whole-array numpy expressions (:meth:`opacity` and a comparison)."""
        prim = np.asarray(prim)
        out = np.zeros(len(prim), bool)
        idx = self._tested(prim)
        if len(idx):
            out[idx] = self.opacity(prim[idx], u[idx], v[idx]) < self.threshold[self.face_material[prim[idx]]]
        return out


def step_past(o_local: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Distances just past hits at ``t`` along rays from float32 tracing-frame origins ``o_local`` (N, 3)."""
    p = np.abs(o_local.astype(np.float64) + d.astype(np.float64) * t[:, None]).max(axis=1)
    scale = np.maximum(p, np.abs(t)).astype(np.float32)
    return t + np.maximum(ALPHA_STEP_ULPS * np.spacing(scale).astype(np.float64), FLOAT_SCALE)
