"""The discrete-event timeline on synthetic stage times, against hand-computed schedules.

The network is netsim with a near-infinite bandwidth and a fixed one-way delay, so a message takes its delay
(plus nanoseconds of serialisation): schedules can be computed by hand to well within 1 µs.
"""
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from suite.harness.method import Clock, Context
from suite.harness.timeline import SimulationError, Timeline, make_network, run_async, run_sync

MS = 1e-3
US = 1e-3  # in ms


def _timeline(delay_ms=10.0, bandwidth_mbps=1e6, clients=1, server=None, timeout_s=0.1):
    net = make_network(f"bw={bandwidth_mbps}mbps,delay={delay_ms}ms", clients=clients, server=server)
    return Timeline(net, message_timeout_s=timeout_s, clients=clients)


def test01_sync_frame_time_is_the_critical_path_with_client_server_overlap():
    # Seed-000 shape: the client G-buffer (20 ms) overlaps pose upload (10 ms) + server visibility (15 ms);
    # then a bitmap (10 ms), then shading (5 ms) on the client.
    tl = _timeline()

    def frame(g):
        g.add_message("pose", 64, "up", after=[])
        g.add_stage("gbuffer", "client", 20 * MS, after=[])
        g.add_stage("visibility", "server", 15 * MS, after=["pose"])
        g.add_message("bitmap", 1000, "down", after=["visibility"])
        g.add_stage("shade", "client", 5 * MS, after=["gbuffer", "bitmap"])

    frames = run_sync(tl, 2, period_s=20 * MS, run_frame=frame)
    # 10 (pose) + 15 (visibility) + 10 (bitmap) + 5 (shade) = 40 ms; gbuffer is off the critical path
    assert frames[0].frame_ms == pytest.approx(40.0, abs=US)
    assert frames[0].latency_ms == pytest.approx(40.0, abs=US)
    assert frames[0].group.critical_path() == ["pose", "visibility", "bitmap", "shade"]
    assert frames[0].group.critical_path_ms() == pytest.approx({"pose": 10, "visibility": 15, "bitmap": 10,
                                                                "shade": 5}, abs=US)
    s = frames[0].group.summary()
    assert s["client_ms"] == pytest.approx(25.0) and s["server_ms"] == pytest.approx(15.0)
    assert s["network_ms"] == pytest.approx(20.0, abs=US) and s["bytes_down"] == 1000
    # the pipeline is slower than the 20 ms period: frame 1 starts when frame 0 is displayed
    assert frames[1].start_s / MS == pytest.approx(40.0, abs=US)
    assert frames[1].frame_interval_ms == pytest.approx(40.0, abs=US)


def test02_stages_on_one_place_serialize_and_on_two_places_overlap():
    tl = Timeline()
    g = tl.group("frame", 0, 0.0)
    a = g.add_stage("a", "client", 10 * MS, after=[])
    b = g.add_stage("b", "client", 10 * MS, after=[])
    c = g.add_stage("c", "server", 10 * MS, after=[])
    assert (a.start_s, b.start_s, c.start_s) == (0.0, pytest.approx(10 * MS), 0.0)
    assert b.binding == "a"  # the stage that held the client
    assert g.critical_path() == ["a", "b"]
    assert g.critical_path_ms() == pytest.approx({"a": 10.0, "b": 10.0})
    assert g.end_s == pytest.approx(20 * MS)


def test03_default_dependency_is_the_previous_event_and_unknown_names_are_rejected():
    tl = Timeline()
    g = tl.group("frame", 0, 0.0)
    g.add_stage("a", "server", 3 * MS)
    b = g.add_stage("b", "client", 2 * MS)  # after=None: chained behind "a"
    assert b.start_s == pytest.approx(3 * MS)
    with pytest.raises(ValueError, match="unknown event 'nope'"):
        g.add_stage("c", "client", 1 * MS, after=["nope"])
    with pytest.raises(ValueError, match="used twice"):
        g.add_stage("a", "client", 1 * MS)
    with pytest.raises(ValueError, match="size must be > 0"):
        g.add_message("empty", 0, "down")


def _async_schedule(max_in_flight, n_frames, lockstep=False):
    # client: 4 ms per frame every 10 ms, sending its pose (10 ms to the server); server update: 27 ms of
    # work, then a message (10 ms to the client)
    tl = _timeline(delay_ms=10.0)

    def send_input(g):
        g.add_message("pose", 64, "up", protocol="udp", after=[])

    def update(g, inputs):
        g.add_stage("render", "server", 27 * MS)
        g.add_message("layers", 1000, "down", protocol="udp")
        return inputs.newest[1]

    def frame(g, u):
        g.add_stage("warp", "client", 4 * MS)

    return run_async(tl, n_frames, 10 * MS, update, frame, run_input=send_input, max_in_flight=max_in_flight,
                     lockstep=lockstep)


def test04_async_updates_start_from_delivered_input_and_the_client_uses_the_newest_arrived_one():
    frames, updates = _async_schedule(max_in_flight=1, n_frames=10)
    # u0: frame 0's pose arrives at 10 -> render 10..37 -> arrives 47.
    # u1 waits for u0's arrival (47); the newest pose there is frame 3's (sent 30, arrived 40) -> arrives 84.
    # u2 at 84: frame 7's pose (arrived 80) is the newest.
    assert [u.start_s / MS for u in updates] == pytest.approx([10, 47, 84], abs=US)
    assert [u.input_frame for u in updates] == [0, 3, 7]
    assert [u.input_s / MS for u in updates] == pytest.approx([0, 30, 70])
    assert [u.arrival_s / MS for u in updates] == pytest.approx([47, 84, 121], abs=US)
    assert [f.update_index for f in frames] == [-1] * 5 + [0] * 4 + [1]
    # a client frame is its own warp; the pose it sends is not part of it
    assert all(f.frame_ms == pytest.approx(4.0) and f.latency_ms == pytest.approx(4.0) for f in frames)
    # staleness = display - input of the update used: 54 - 0 ... 94 - 30
    assert frames[5].staleness_ms == pytest.approx(54.0) and frames[9].staleness_ms == pytest.approx(64.0)
    assert math.isnan(frames[0].staleness_ms)


def test05_pipelined_updates_overlap_compute_with_transfer():
    frames, updates = _async_schedule(max_in_flight=2, n_frames=12)
    # u1 starts when the server is free (37 ms), with the newest pose there (frame 2's, arrived 30);
    # u2 waits for u0's arrival (47) and the server (64): frame 5's pose (arrived 60) is the newest;
    # u3 waits for u1's arrival (74) and the server (91): frame 8's pose (arrived 90)
    assert [u.start_s / MS for u in updates] == pytest.approx([10, 37, 64, 91], abs=US)
    assert [u.input_frame for u in updates] == [0, 2, 5, 8]
    assert [u.arrival_s / MS for u in updates] == pytest.approx([47, 74, 101, 128], abs=US)


def test06_lockstep_zero_latency_frame_uses_an_update_made_from_its_own_input():
    tl = Timeline()  # netsim's ideal network
    frames, updates = run_async(tl, 2, 10 * MS,
                                lambda g, inputs: g.add_stage("render", "server", 25 * MS),
                                lambda g, u: g.add_stage("warp", "client", 4 * MS),
                                run_input=lambda g: g.add_message("pose", 64, "up", after=[]), lockstep=True)
    assert [f.update_index for f in frames] == [0, 1]
    assert [u.input_frame for u in updates] == [0, 1]
    assert [u.start_s / MS for u in updates] == pytest.approx([0, 29])
    assert [f.latency_ms for f in frames] == pytest.approx([29, 29])
    assert [f.staleness_ms for f in frames] == pytest.approx([29, 29])


def test07_clients_share_the_server_and_each_has_its_own_client_place():
    # two sync clients, each: its pose (10 ms) then 30 ms on the server then 4 ms on its own client
    tl = _timeline(clients=2)

    def frame(g):
        g.add_message("pose", 64, "up", after=[])
        g.add_stage("render", "server", 30 * MS)
        g.add_stage("show", "client", 4 * MS)

    frames = run_sync(tl, 1, 100 * MS, frame)
    a, b = sorted(frames, key=lambda f: f.client)
    # client 0 holds the server 10..40; client 1's render waits for it: 40..70
    assert a.display_s / MS == pytest.approx(44, abs=US) and b.display_s / MS == pytest.approx(74, abs=US)
    assert b.group.events["render"].binding == "server busy"
    # client stages of the two clients would overlap: each client is its own place
    assert a.group.events["show"].place == "client" and b.group.events["show"].client == 1


def test08_a_message_that_never_arrives_releases_dependants_after_the_timeout():
    # 100 kB over UDP at 1 Mbit/s takes 0.8 s; the receiver waits 0.1 s for it
    tl = _timeline(delay_ms=5.0, bandwidth_mbps=1.0, timeout_s=0.1)
    g = tl.group("frame", 0, 0.0)
    ev, d = g.add_message("m", 100_000, "down", protocol="udp")
    after = g.add_stage("use", "client", 1 * MS)
    assert not ev.complete
    assert 0 < ev.delivered_bytes < 0.15 * 100_000  # only what arrived within 100 ms (about 11.9 kB)
    assert ev.end_s <= 0.1 + 1e-9 and after.start_s == pytest.approx(ev.end_s)
    assert sum(end - start for start, end in ev.lost_ranges) == 100_000 - ev.delivered_bytes


def test09_a_loop_reads_a_message_only_when_the_clock_has_reached_its_arrival():
    tl = _timeline(delay_ms=10.0)
    seen = []

    def frame(g):
        ctx = Context(g, scene=None, tracer=None, t_s=0.0, prev_t_s=None, resolution=(4, 2), seed=0, params={},
                      zero_latency=False, clock=Clock())
        msg = ctx.send("data", b"abc", direction="down", after=[])
        seen.append(tl.sched.now_s)
        assert msg.data == b"abc"        # outside a stage: waits for the arrival
        seen.append(tl.sched.now_s)
        ctx.modelled_stage("think", place="client", duration_ms=5.0, after=["data"])
        late = ctx.send("late", b"x", direction="down", after=["think"])  # arrives at 25 ms
        with pytest.raises(SimulationError, match="before it arrived"):
            with ctx.stage("peek", place="client", after=[]):
                late.data  # a stage that does not depend on the message may not read it
        with ctx.stage("use", place="client", after=["late"]):
            pass
        return None

    run_sync(tl, 1, 0.1, frame)
    assert seen[0] == 0.0 and seen[1] / MS == pytest.approx(10.0, abs=US)


_stages = st.lists(st.tuples(st.sampled_from(["client", "server"]), st.integers(0, 50)), min_size=1, max_size=8)


@settings(max_examples=60, deadline=None)
@given(_stages)
def test10_a_chain_takes_the_sum_and_independent_stages_the_busier_place(stages):
    chain = Timeline().group("frame", 0, 0.0)
    for k, (place, ms) in enumerate(stages):
        chain.add_stage(f"s{k}", place, ms * MS)
    assert chain.end_s == pytest.approx(sum(ms for _, ms in stages) * MS)

    parallel = Timeline().group("frame", 0, 0.0)
    for k, (place, ms) in enumerate(stages):
        parallel.add_stage(f"s{k}", place, ms * MS, after=[])
    busiest_ms = max(sum(ms for p, ms in stages if p == place) for place in ("client", "server"))
    assert parallel.end_s == pytest.approx(busiest_ms * MS)


def test11_updates_never_repeat_an_input_even_when_they_cost_nothing():
    tl = Timeline()  # ideal: a message-only update takes zero time
    frames, updates = run_async(tl, 3, 10 * MS, lambda g, inputs: g.add_message("m", 10, "down"),
                                lambda g, u: g.add_stage("warp", "client", 1 * MS),
                                run_input=lambda g: g.add_message("pose", 64, "up", after=[]), max_in_flight=4)
    # each update has its own input; the update made from frame i's input arrives after frame i started (the
    # frame samples its input and then shows what had arrived), and frame 2 is the last: no update follows it
    assert [u.input_frame for u in updates] == [0, 1]
    assert [f.update_index for f in frames] == [-1, 0, 1]


def test12_a_stage_waits_for_its_device_work_before_its_clock_stops():
    """Dr.Jit kernels run asynchronously: the stage's block ends, then the tracer's device is waited for, then the
    stage's wall time is taken (the work is billed to the stage that launched it)."""
    import time

    order = []

    class Device:
        def sync(self):
            time.sleep(0.02)  # the device still running the stage's kernels
            order.append("sync")

    tracer = type("Tracer", (), {"device": Device(), "counters": {}})()
    walls = []

    def frame(g):
        ctx = Context(g, scene=None, tracer=tracer, t_s=0.0, prev_t_s=None, resolution=(4, 2), seed=0, params={},
                      zero_latency=False, clock=Clock())
        with ctx.stage("launch", place="client", after=[]):
            order.append("block")
        walls.append(ctx.stages[-1].wall_ms)
        return None

    run_sync(_timeline(delay_ms=1.0), 1, 0.1, frame)
    assert order == ["block", "sync"] and walls[0] >= 20.0
