"""The server's path-tracing renderer (``renderer = "path"``): Mitsuba 3's ``path`` integrator at a few samples
per pixel, denoised with the suite's edge-avoiding a-trous filter guided by the G-buffer.

1. **Path tracing** (stage ``render``): the scene at the frame's time and the pose the server received, converted
   with :func:`suite.core.scene.mitsuba_io.to_mitsuba_dict` (the conversion the references use, so the same
   triangles, materials, lights and camera; ``volpath`` for alpha-tested scenes,
   :func:`suite.core.reference.alpha_aware_integrator`), rendered with ``path_spp`` samples per pixel in up to 4
   passes (:func:`suite.core.reference.render_with_stderr`), which also give each pixel's standard error.
2. **Denoising** (stage ``denoise``, with ``path_denoise``): the pixel-centre G-buffer of the same pose
   (:func:`suite.core.gbuffer.render_gbuffer`); the radiance is demodulated by the albedo (illumination =
   radiance / albedo; mirrors and glass are filtered as radiance) and filtered by
   :func:`suite.core.denoise.atrous` on the G-buffer's depth and normals, with the luminance variance of the
   demodulated estimate from the passes' standard error (one pass: the bilateral 5x5 spatial estimate,
   :func:`suite.core.denoise.spatial_variance`); the albedo is
   multiplied back in. Pixels that see an emitter or no surface pass through unfiltered and are never taps. On
   a Mitsuba llvm/cuda tracer the filters run as Dr.Jit kernels (:mod:`suite.core.device.denoise`).

This is the spatial half of SVGF (Schied et al. 2017 §4.4); there is no temporal accumulation, so every frame is
denoised from its own samples (no ghosting, more residual noise at low spp).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.core import denoise

MAX_PASSES = 4


@dataclass
class PathFrame:
    noisy: np.ndarray           # (H, W, 3) the path tracer's mean radiance
    stderr: np.ndarray          # (H, W, 3) its standard error per pixel (inf with one pass)


def path_trace(scene, t_s: float, resolution, spp: int, max_depth: int, seed: int) -> PathFrame:
    """Stage 1 of the module docstring."""
    from suite.core.reference import alpha_aware_integrator, render_with_stderr
    from suite.core.scene.mitsuba_io import to_mitsuba_dict

    integrator = alpha_aware_integrator(scene, {"type": "path", "max_depth": int(max_depth)})
    scene_dict = to_mitsuba_dict(scene, t_s=float(t_s), resolution=tuple(resolution), integrator=integrator,
                                 spp=int(spp))
    mean, stderr = render_with_stderr(scene_dict, int(spp), passes=min(int(spp), MAX_PASSES), seed=int(seed))
    return PathFrame(mean, stderr)


def denoise_frame(frame: PathFrame, g, settings: denoise.AtrousSettings, device=None) -> np.ndarray:
    """Stage 2 of the module docstring: the denoised radiance, from the path frame and the G-buffer ``g``. With a
    Dr.Jit ``device`` (a Mitsuba llvm/cuda tracer's) the filters run as its kernels (suite.core.device.denoise:
    the same values to rounding; inputs and results are counted copies)."""
    if device is not None:
        from suite.core.device import denoise as dden

        atrous = lambda *a: dden.atrous_arrays(device, *a)  # noqa: E731
        spatial_variance = lambda *a: dden.spatial_variance_arrays(device, *a)  # noqa: E731
    else:
        atrous, spatial_variance = denoise.atrous, denoise.spatial_variance
    from suite.core.scene.model import KIND_CODES

    emits = g.emission.max(axis=-1) > 0
    filtered = g.valid & ~emits
    specular = np.isin(g.kind, [KIND_CODES["mirror"], KIND_CODES["glass"]]) if g.kind is not None \
        else np.zeros(g.valid.shape, bool)
    albedo = np.where(filtered[..., None] & ~specular[..., None] & (g.albedo > 1e-3), g.albedo, 1.0)
    illum = (frame.noisy / albedo).astype(np.float32)
    if np.isfinite(frame.stderr).all():
        variance = denoise.luminance(frame.stderr / albedo) ** 2
    else:
        variance = spatial_variance(denoise.luminance(illum), g.depth, g.normal, filtered)
    out, _, _ = atrous(illum, variance, np.where(filtered, g.depth, 0.0), g.normal, filtered, settings)
    return np.where(filtered[..., None], out * albedo, frame.noisy).astype(np.float32)
