"""Ray-tracing backends behind one interface (see :mod:`suite.core.trace.base`).

``make(backend, scene)`` with backend ``embree`` or ``mitsuba`` (variant auto: CUDA if a GPU is usable, else
LLVM), or an explicit ``mitsuba-llvm``, ``mitsuba-cuda``, ``mitsuba-scalar``.
"""
from __future__ import annotations

from suite.errors import UserError
from suite.core.trace.base import Hits, Tracer
from suite.core.trace.robust import offset_ray_origin

BACKENDS = {
    "embree": "Embree 4 via embreex (CPU, one thread)",
    "mitsuba": "Mitsuba 3 / Dr.Jit, variant chosen automatically (cuda_ad_rgb with a GPU, else llvm_ad_rgb)",
    "mitsuba-llvm": "Mitsuba 3 / Dr.Jit llvm_ad_rgb (CPU, vectorised, multi-threaded)",
    "mitsuba-cuda": "Mitsuba 3 / Dr.Jit cuda_ad_rgb (NVIDIA GPU)",
    "mitsuba-scalar": "Mitsuba 3 scalar_rgb, one ray at a time (last resort when neither LLVM nor CUDA works; slow)",
}

__all__ = ["make", "list_backends", "Hits", "Tracer", "offset_ray_origin", "BACKENDS"]


def list_backends() -> dict[str, str]:
    return dict(BACKENDS)


def make(backend: str, scene) -> Tracer:
    if backend == "embree":
        from suite.core.trace.embree import EmbreeTracer

        return EmbreeTracer(scene)
    if backend == "mitsuba" or backend.startswith("mitsuba-"):
        from suite.core.trace.mitsuba_backend import MitsubaTracer

        variant = "auto" if backend == "mitsuba" else backend.split("-", 1)[1]
        return MitsubaTracer(scene, variant=variant)
    raise UserError(f"unknown backend '{backend}' (choose from {', '.join(BACKENDS)})")
