"""The recording tracer of the benchmarks (suite.core.trace.recording) keeps the rays of every query in the tracing
frame, so that the backend's raw entry points, replaying the log, trace the very rays the stage traced."""
import numpy as np
import pytest

from suite.core.scene import load
from suite.core.trace import make
from suite.core.trace.base import as_rays
from suite.core.trace.recording import RecordingTracer


@pytest.fixture(scope="module")
def scene_tracer():
    scene = load("living_room")
    return scene, make("embree", scene)


def _rays(scene, n=500, seed=1):
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds()
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d.astype(np.float32)


def test01_every_query_is_forwarded_and_logged_in_the_raw_layout(scene_tracer):
    scene, tracer = scene_tracer
    rec = RecordingTracer(tracer)
    o, d = _rays(scene)
    tmin = np.full(len(o), 0.05, np.float32)
    h = rec.intersect(o, d, tmin, 4.0)
    blocked = rec.occluded(o, d, 0.0, 2.5)
    ro, rd, _, rlen = as_rays(o, d, 0.0, 2.5, tracer.shift)
    blocked_local = rec.occluded_local(ro.copy(), rd.copy(), rlen.copy())
    h_local = rec.intersect_local(ro.copy(), rd.copy(), rlen.copy())
    assert [k for k, *_ in rec.log] == ["i", "o", "o", "i"] and rec.rays == 4 * len(o)
    assert np.array_equal(h.prim, tracer.intersect(o, d, tmin, 4.0).prim)
    assert np.array_equal(blocked, tracer.occluded(o, d, 0.0, 2.5)) and np.array_equal(blocked, blocked_local)
    for kind, lo, ld, ll in rec.log:
        assert lo.shape == ld.shape == (len(o), 3) and ll.shape == (len(o),)
        assert lo.dtype == ld.dtype == ll.dtype == np.float32 and lo.flags.c_contiguous
    # tmin advanced the first query's origins and shortened its lengths, as the backend saw them
    _, lo, _, ll = rec.log[0]
    eo, _, _, el = as_rays(o, d, tmin, 4.0, tracer.shift)
    assert np.array_equal(lo, eo) and np.array_equal(ll, el)
    assert np.array_equal(h_local.prim, tracer.intersect_local(ro.copy(), rd.copy(), rlen.copy()).prim)


def test02_the_log_is_a_copy_the_callers_buffers_and_the_backend_cannot_change(scene_tracer):
    scene, tracer = scene_tracer
    rec = RecordingTracer(tracer)
    o, d = _rays(scene, seed=2)
    ro, rd, _, rlen = as_rays(o, d, 0.0, np.inf, tracer.shift)
    expect = tracer.intersect_local(ro.copy(), rd.copy(), rlen.copy())
    buf_o, buf_d, buf_len = ro.copy(), rd.copy(), rlen.copy()
    rec.intersect_local(buf_o, buf_d, buf_len)   # embreex writes its hit distances into buf_len
    buf_o[:], buf_d[:] = 0.0, 1.0                 # and the caller reuses its buffers
    _, lo, ld, ll = rec.log[0]
    assert np.array_equal(lo, ro) and np.array_equal(ld, rd) and np.array_equal(ll, rlen)
    again = tracer.intersect_local(lo, ld, ll.copy())
    assert np.array_equal(again.prim, expect.prim) and np.array_equal(again.t, expect.t)
    buf_d = d.copy()
    rec.intersect(o, buf_d)  # float32 directions: the backend's layout already, not copied on the way to it
    buf_d[:] = 0.0
    assert np.array_equal(rec.log[-1][2], d)


def test03_replay_traces_the_log_on_the_raw_entry_points(scene_tracer):
    scene, tracer = scene_tracer
    calls = []

    class Raw:  # the backend's raw entry points, watched
        def raw_intersect(self, o, d, length):
            calls.append(("i", o, d, length.copy()))  # as given: embreex writes its hit distances into it
            return tracer.raw_intersect(o, d, length)

        def raw_occluded(self, o, d, length):
            calls.append(("o", o, d, length.copy()))
            return tracer.raw_occluded(o, d, length)

    rec = RecordingTracer(tracer)
    o, d = _rays(scene, seed=3)
    rec.intersect(o, d)
    rec.occluded(o, d, 0.0, 1.0)
    rec.replay(Raw())
    rec.replay(Raw())  # twice: a closest-hit replay leaves the logged lengths as they were
    assert [c[0] for c in calls] == ["i", "o", "i", "o"]
    for (kind, lo, ld, ll), (ck, co, cd, cl) in zip(rec.log * 2, calls):
        assert kind == ck and co is lo and cd is ld and np.array_equal(cl, ll)
    _, _, _, ll = rec.log[0]
    assert np.array_equal(ll, as_rays(o, d, 0.0, np.inf, tracer.shift)[3])


def test04_local_entry_points_and_the_device_follow_the_wrapped_tracer(scene_tracer):
    class Plain:  # a tracer without local entry points, with a device
        shift, counters, device = None, {}, object()

        def intersect(self, *a):
            raise AssertionError("not called")

        occluded = intersect

    rec = RecordingTracer(Plain())
    assert not hasattr(rec, "intersect_local") and not hasattr(rec, "occluded_local")
    assert not hasattr(rec, "device")  # by default the stage sees a host tracer: its queries pass through here
    assert RecordingTracer(Plain(), device=True).device is Plain.device
    assert rec.counters is Plain.counters  # other attributes are the wrapped tracer's
    _, tracer = scene_tracer
    assert hasattr(RecordingTracer(tracer), "intersect_local") and hasattr(RecordingTracer(tracer), "occluded_local")
