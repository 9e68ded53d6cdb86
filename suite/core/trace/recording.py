"""A tracer that records the rays of every query, for benchmarks that time a stage against the backend's raw entry
points on the very rays the stage traced (``raw_intersect`` / ``raw_occluded``: the "raw" of every ray-rate ratio,
:data:`suite.core.trace.bench.RAY_RATE_GOAL`).

The stage runs once on a :class:`RecordingTracer` (outside every timed run); its log then replays on the backend
alone (:meth:`RecordingTracer.replay`), interleaved with timed runs of the stage on the plain tracer.
"""
from __future__ import annotations

import numpy as np


class RecordingTracer:
    """Wraps a tracer: forwards every query and keeps its rays in the tracing frame and the raw entry points' layout
    (``log``: ``("i" | "o", origins (N, 3), directions (N, 3), lengths (N,))``, float32, fresh copies: callers reuse
    their buffers and embreex overwrites the lengths it is given).

    ``intersect_local`` and ``occluded_local`` exist exactly when the wrapped tracer has them, so a stage takes the
    code path it takes on the plain tracer. Other attributes are the wrapped tracer's, except ``device`` unless
    ``device`` is true: a stage that finds a Dr.Jit device queries the scene on it directly, past this wrapper, so
    by default it sees a host tracer and takes its host path (whose queries are the ones recorded)."""

    def __init__(self, tracer, device: bool = False):
        self.__dict__["_device"] = bool(device)  # before anything can reach __getattr__
        self.tracer = tracer
        self.log: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
        if hasattr(tracer, "occluded_local"):
            self.occluded_local = self._occluded_local
        if hasattr(tracer, "intersect_local"):
            self.intersect_local = self._intersect_local

    def __getattr__(self, name):
        if name == "device" and not self._device:
            raise AttributeError(name)
        if name in ("occluded_local", "intersect_local"):  # the wrapped tracer has none (see __init__)
            raise AttributeError(name)
        return getattr(self.tracer, name)

    @property
    def rays(self) -> int:
        """Rays recorded so far."""
        return int(sum(len(d) for _, _, d, _ in self.log))

    # ------------------------------------------------------------------------------------------ queries
    def intersect(self, o, d, tmin=0.0, tmax=np.inf):
        self._keep("i", o, d, tmin, tmax)
        return self.tracer.intersect(o, d, tmin, tmax)

    def occluded(self, o, d, tmin=0.0, tmax=np.inf):
        self._keep("o", o, d, tmin, tmax)
        return self.tracer.occluded(o, d, tmin, tmax)

    def _intersect_local(self, o, d, length):
        self._keep_local("i", o, d, length)
        return self.tracer.intersect_local(o, d, length)

    def _occluded_local(self, o, d, length):
        self._keep_local("o", o, d, length)
        return self.tracer.occluded_local(o, d, length)

    def _keep(self, kind, o, d, tmin, tmax):
        from suite.core.trace.base import as_rays

        # as_rays without scratch buffers: fresh origins and lengths; the directions may be the caller's own array
        ro, rd, _, rlen = as_rays(o, d, tmin, tmax, getattr(self.tracer, "shift", None))
        self.log.append((kind, ro, np.array(rd, np.float32, order="C"), rlen))

    def _keep_local(self, kind, o, d, length):
        soa = bool(getattr(self.tracer, "soa_origins", False))
        self.log.append((kind, np.array(o.T if soa else o, np.float32, order="C"),
                         np.array(d, np.float32, order="C"), np.array(length, np.float32, order="C")))

    # ------------------------------------------------------------------------------------------ replay
    def replay(self, tracer=None, log=None) -> None:
        """The recorded queries (or ``log``, a part of them) on the raw entry points of ``tracer`` (default: the
        wrapped one), in their order. A closest-hit query gets a copy of its lengths (embreex writes its hit
        distances into them)."""
        tracer = self.tracer if tracer is None else tracer
        for kind, o, d, length in self.log if log is None else log:
            if kind == "i":
                tracer.raw_intersect(o, d, length.copy())
            else:
                tracer.raw_occluded(o, d, length)


def device_replay(dev, log=(), records=()):
    """(rays, replay) on a Dr.Jit ``dev``: the queries of ``log`` (:attr:`RecordingTracer.log` entries, uploaded once,
    here) and ``records`` (``("i" | "o", Ray3f)`` already in device memory) on the backend's raw
    ``ray_intersect_preliminary`` / ``ray_test`` of Dr.Jit arrays: the "raw" of a ratio on a Mitsuba llvm/cuda
    backend (rays that stay in the backend's memory). ``replay()`` returns the seconds the calls took, each timed to
    its end."""
    import time

    calls = [(kind, dev.raw_ray(dev.to_device(o, dev.Point3f), dev.to_device(d, dev.Vector3f),
                                dev.to_device(np.asarray(length, np.float32), dev.Float)))
             for kind, o, d, length in log]
    calls += list(records)
    rays = int(sum(dev.dr.width(ray.d) for _, ray in calls))

    def replay() -> float:
        elapsed = 0.0
        for kind, ray in calls:
            t0 = time.perf_counter()
            (dev.raw_intersect if kind == "i" else dev.raw_occluded)(ray)
            elapsed += time.perf_counter() - t0
        return elapsed

    return rays, replay
