"""Ray-tracing backends behind one interface (see :mod:`suite.core.trace.base`).

``make(backend, scene)`` with backend ``embree`` or ``mitsuba`` (variant auto: CUDA if a GPU is usable, else
LLVM), or an explicit ``mitsuba-llvm``, ``mitsuba-cuda``, ``mitsuba-scalar``. ``backend_status()`` says which work
on this machine (and what ``mitsuba`` resolves to); ``backend_params(...)`` makes pytest parameters that skip the
others with their reason. Mitsuba tracers of the vectorised variants also have ``tracer.device``
(:mod:`suite.core.device`): the queries and the core kernels on device-resident Dr.Jit arrays.
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

__all__ = ["make", "list_backends", "backend_status", "Hits", "Tracer", "offset_ray_origin", "BACKENDS"]


def list_backends() -> dict[str, str]:
    return dict(BACKENDS)


def backend_status() -> dict[str, dict]:
    """Per backend on this machine: ``{"available": bool, "detail": str}``; for ``mitsuba`` the detail names the
    variant ``auto`` resolves to. Cheap: imports the libraries and asks Dr.Jit which backends initialise, compiles
    nothing."""
    out = {}
    try:
        import embreex  # noqa: F401

        out["embree"] = {"available": True, "detail": "embreex imports"}
    except Exception as exc:  # noqa: BLE001 - any import problem means "not available"
        out["embree"] = {"available": False, "detail": f"embreex does not import ({exc})"}
    try:
        from suite.core.env import variant_status

        variants = variant_status()
    except Exception as exc:  # noqa: BLE001
        reason = f"Mitsuba / Dr.Jit do not import ({exc})"
        return {**out, **{b: {"available": False, "detail": reason} for b in BACKENDS if b != "embree"}}
    auto = variants["auto"]
    out["mitsuba"] = {"available": auto["available"],
                      "detail": f"auto -> {auto['variant']} ({auto['detail']})" if auto["available"] else auto["detail"],
                      "variant": auto["variant"]}
    for short in ("llvm", "cuda", "scalar"):
        st = variants[short]
        out[f"mitsuba-{short}"] = {"available": st["available"], "detail": st["detail"], "variant": st["variant"]}
    return out


def device_backends() -> list[str]:
    """The backends with a Dr.Jit device path that work on this machine (``mitsuba-llvm``; ``mitsuba-cuda`` with a
    GPU): what benchmarks time the device kernels on."""
    status = backend_status()
    return [b for b in ("mitsuba-llvm", "mitsuba-cuda") if status.get(b, {}).get("available")]


def backend_params(*names):
    """pytest parameters for backend names, each skipped with its reason where it does not work on this machine
    (``mitsuba-cuda`` without a GPU). For backend-parametrised tests."""
    import pytest

    status = backend_status()
    out = []
    for name in names:
        st = status.get(name, {"available": True})
        out.append(name if st["available"] else
                   pytest.param(name, marks=pytest.mark.skip(reason=f"backend {name} unavailable: {st['detail']}")))
    return out


def make(backend: str, scene) -> Tracer:
    if backend == "embree":
        from suite.core.trace.embree import EmbreeTracer

        return EmbreeTracer(scene)
    if backend == "mitsuba" or backend.startswith("mitsuba-"):
        from suite.core.trace.mitsuba_backend import MitsubaTracer

        variant = "auto" if backend == "mitsuba" else backend.split("-", 1)[1]
        return MitsubaTracer(scene, variant=variant)
    raise UserError(f"unknown backend '{backend}' (choose from {', '.join(BACKENDS)})")
