"""Host pipelines: backend queries on the caller's thread, the work around them on one worker thread.

The host path of a pass (Embree, or Mitsuba fed from numpy) is a chain per batch of rays: make the rays, query the
backend, compute from the hits. On two cores the backend's query and the work around it can overlap, as long as
the backend is queried from one thread, one query after the other, so that its ray stream stays the one a plain
loop would send (and a raw replay of those queries times the same work). :func:`pipelined` runs independent steps
``(make, trace, finish)``, as the row chunks of an image (:func:`suite.core.gbuffer.row_steps`) or the views of a
PVS.

Chains of dependent queries (depth peeling: each layer's query made from the previous one's hits) were tried as
two interleaved streams of alternate pixel blocks: the backend took about 4 % longer on the streams' smaller and
less coherent queries and the streams fell out of step at every layer's end, so it was no faster than one chain
(Dabrovic Sponza 480x270, 8 layers: 166 against 161 ms), and peeling stays one chain.

Passes whose batches are chains of dependent queries of their own (a path tracer's bounces, specular chains) run
their independent parts on threads instead, each part's queries under one lock (:class:`SerialTracer`), so that one
part's compiled passes overlap another's query.

Rays are handed to the backend in its own frame and layout (:func:`local_rays`, then ``intersect_local``), made on
the worker, so the tracing thread only queries. The worker is kept for the process; a pipeline started while it
serves another (another thread's, or from inside a step) gets a thread of its own.
"""
from __future__ import annotations

import os
import threading
from contextlib import contextmanager

import numpy as np

from suite.core.trace.base import Hits, as_rays


def local_rays(tracer, origins, dirs, tmax=np.inf):
    """Rays from their origins (no tmin) to ``tmax`` in ``tracer``'s frame and layout, the arguments of its
    ``intersect_local`` and ``occluded_local``, in fresh arrays (made on another thread than the one that queries,
    or outside the lock a shared tracer is queried under); None for a tracer without both (the caller then uses
    ``intersect`` / ``occluded``: :func:`trace_local`)."""
    if not (hasattr(tracer, "intersect_local") and hasattr(tracer, "occluded_local")):
        return None
    o, d, _, length = as_rays(origins, dirs, 0.0, tmax, tracer.shift, bool(getattr(tracer, "soa_origins", False)))
    return o, d, length


def trace_local(tracer, query, origins, dirs) -> Hits:
    """Closest hits of the rays ``(origins, dirs)``: ``tracer.intersect_local(*query)`` with the query
    :func:`local_rays` made of them (the same rays, queries and hits as ``tracer.intersect(origins, dirs)``)."""
    return tracer.intersect(origins, dirs) if query is None else tracer.intersect_local(*query)



class SerialTracer:
    """A tracer whose queries run one at a time under ``lock``, for passes whose parts run on threads of their own
    (their compiled passes releasing the GIL beside another part's query): one stream of rays whatever thread sends
    them (and the tracer's scratch buffers and counters are touched by one query at a time). It has the tracer's
    queries (``intersect``, ``occluded`` and the ``*_local`` ones where the tracer has them), each under the lock;
    everything else is the tracer's. ``queried`` is set once a query has taken the lock.

    Where parts outnumber the cores, each part's thread runs its work inside :meth:`part`: its passes take one of
    ``cores`` slots (default: every core but one), which its queries give up while they wait for and hold the
    tracer, so the query always has a core of its own. Unbounded, three parts on two cores ran two parts' passes
    beside a query and the query's thread shared a core (the layered path tracer on Dabrovic Sponza 480x270, 4
    layers, Embree: 0.845 of the raw rate unbounded, 0.88 with one slot). With no more parts than cores the slots
    only make a part that has finished its query wait for one (the two-part specular chains on gallery 320x180, two
    interleaved runs: 0.655 and 0.611 unbounded, 0.637 and 0.591 with one slot), and those parts run outside
    :meth:`part`."""

    QUERIES = ("intersect", "occluded", "intersect_local", "occluded_local")

    def __init__(self, tracer, lock, cores: int | None = None):
        self.tracer, self.lock = tracer, lock
        self.queried = threading.Event()  # set when a query first holds the lock
        self._cores = threading.Semaphore(max((os.cpu_count() or 2) - 1, 1) if cores is None else max(int(cores), 1))
        self._in_part = threading.local()
        for name in self.QUERIES:
            if hasattr(tracer, name):
                setattr(self, name, self._locked(getattr(tracer, name)))

    @contextmanager
    def part(self):
        """The calling thread's work as one part: its passes on a core slot, given up during its queries."""
        self._cores.acquire()
        self._in_part.on = True
        try:
            yield self
        finally:
            self._in_part.on = False
            self._cores.release()

    def _locked(self, query):
        def call(*args, **kwargs):
            in_part = getattr(self._in_part, "on", False)
            if in_part:
                self._cores.release()
            try:
                with self.lock:
                    self.queried.set()
                    return query(*args, **kwargs)
            finally:
                if in_part:
                    self._cores.acquire()
        return call

    def __getattr__(self, name):
        if name in self.QUERIES:  # one the tracer lacks: not reached through to it unlocked
            raise AttributeError(name)
        return getattr(self.tracer, name)


# The worker thread of the pipelines, kept for the process (made on first use; a forked child makes its own).
_WORKER = {"lock": threading.Lock(), "pool": None, "pid": None}


@contextmanager
def kept_worker():
    """A one-thread executor: the process's kept worker when it is free, else one of the caller's own (the kept one
    serves another thread's pipeline, or the pipeline whose step started this caller). For :func:`pipelined` and
    for passes that run one part on a second thread."""
    from concurrent.futures import ThreadPoolExecutor

    if not _WORKER["lock"].acquire(blocking=False):
        with ThreadPoolExecutor(1, thread_name_prefix="splitbench-pipeline") as pool:
            yield pool
        return
    try:
        if _WORKER["pool"] is None or _WORKER["pid"] != os.getpid():  # none yet, or the parent process's
            _WORKER["pool"] = ThreadPoolExecutor(1, thread_name_prefix="splitbench-pipeline")
            _WORKER["pid"] = os.getpid()
        yield _WORKER["pool"]
    finally:
        _WORKER["lock"].release()


# How many steps' rays the pipeline makes ahead of the step being traced (:func:`pipelined`): enough that the
# backend never waits for rays, few enough that a pipeline of whole views keeps little memory.
PIPELINE_LOOKAHEAD = 2


def pipelined(steps) -> None:
    """Runs ``[(make, trace, finish)]`` steps pipelined on two threads. The caller's thread traces the steps one
    after the other (the backend is queried from it only, in step order, so its ray stream is the one a pass
    over the whole image would send). One worker makes the rays of the next steps (up to
    :data:`PIPELINE_LOOKAHEAD` ahead, first, so that the backend does not wait) and finishes the traced ones in
    between; once everything is traced the caller's thread finishes steps too. Makes and finishes are compiled
    passes that release the GIL; they must not query the backend, and steps write disjoint outputs (a finish may
    run beside another step's make or finish). Each step's calls are the ones a pass over its whole image would
    make for its rows, so the results do not depend on the chunking, on which thread ran a call, nor on the
    images whose steps share the pipeline."""
    if not steps:
        return
    if len(steps) == 1:
        for call in steps[0]:
            call()
        return
    n = len(steps)
    cond = threading.Condition()
    # Progress, guarded by cond: makes claimed (in order), makes done, steps traced, finishes claimed (in order).
    state = {"make": 0, "made": [False] * n, "traced": 0, "finish": 0, "error": None}

    def run(kind, k):
        try:
            steps[k][kind]()
        except BaseException as exc:  # handed to the caller's thread, which raises it
            with cond:
                state["error"] = state["error"] or exc
                cond.notify_all()
            return False
        if kind == 0:
            with cond:
                state["made"][k] = True
                cond.notify_all()
        return True

    def claim_finish():
        """The next finish that may run (its step traced), claimed; None if there is none now."""
        k = state["finish"]
        if k < state["traced"]:
            state["finish"] = k + 1
            return k
        return None

    def worker():
        while True:
            with cond:
                while True:
                    if state["error"] is not None or state["finish"] >= n:
                        return
                    k = state["make"]
                    if k < n and k <= state["traced"] + PIPELINE_LOOKAHEAD:
                        state["make"], kind = k + 1, 0
                        break
                    k = claim_finish()
                    if k is not None:
                        kind = 2
                        break
                    cond.wait()
            if not run(kind, k):
                return

    with kept_worker() as pool:
        done = pool.submit(worker)
        _trace_steps(steps, state, cond, run, claim_finish)
        done.result()
    if state["error"] is not None:
        raise state["error"]


def _trace_steps(steps, state, cond, run, claim_finish) -> None:
    """The caller's side of :func:`pipelined`: every step's query in order, then finishes beside the worker."""
    n = len(steps)
    try:
        for k in range(n):
            with cond:
                mine = state["make"] == k  # not claimed by the worker yet: make it here rather than wait
                if mine:
                    state["make"] = k + 1
            if mine and not run(0, k):
                break
            with cond:
                while not state["made"][k] and state["error"] is None:
                    cond.wait()
                if state["error"] is not None:
                    break
            steps[k][1]()
            with cond:
                state["traced"] = k + 1
                cond.notify_all()
        while True:  # everything traced: finish beside the worker
            with cond:
                k = None if state["error"] is not None else claim_finish()
            if k is None or not run(2, k):
                break
    except BaseException as exc:
        with cond:
            state["error"] = state["error"] or exc
            cond.notify_all()
