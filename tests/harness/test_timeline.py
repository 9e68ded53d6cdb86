"""The discrete-event timeline on synthetic stage times, against hand-computed schedules."""
import math

import pytest

from suite.harness.timeline import IdealLink, Timeline, run_async, run_sync

MS = 1e-3


def _links(bandwidth_mbps=math.inf, delay_ms=10.0):
    link = IdealLink(bandwidth_mbps=bandwidth_mbps, delay_ms=delay_ms)
    return {"down": link, "up": link}


def test01_sync_frame_time_is_the_critical_path_with_client_server_overlap():
    # Seed-000 shape: the client G-buffer (20 ms) overlaps pose upload (10 ms) + server visibility (15 ms);
    # then a 1000-byte bitmap at 8 Mbit/s (1 ms) + 10 ms delay, then shading (5 ms) on the client.
    tl = Timeline(_links(bandwidth_mbps=8.0, delay_ms=10.0))

    def frame(g):
        g.add_message("pose", 0, "up", after=[])
        g.add_stage("gbuffer", "client", 20 * MS, after=[])
        g.add_stage("visibility", "server", 15 * MS, after=["pose"])
        g.add_message("bitmap", 1000, "down", after=["visibility"])
        g.add_stage("shade", "client", 5 * MS, after=["gbuffer", "bitmap"])

    frames = run_sync(tl, 2, period_s=20 * MS, run_frame=frame)
    # 10 (pose) + 15 (visibility) + 1 + 10 (bitmap) + 5 (shade) = 41 ms; gbuffer is off the critical path
    assert frames[0].frame_ms == pytest.approx(41.0)
    assert frames[0].latency_ms == pytest.approx(41.0)
    assert frames[0].group.critical_path() == ["pose", "visibility", "bitmap", "shade"]
    assert frames[0].group.critical_path_ms() == pytest.approx({"pose": 10, "visibility": 15, "bitmap": 11,
                                                                "shade": 5})
    s = frames[0].group.summary()
    assert s["client_ms"] == pytest.approx(25.0) and s["server_ms"] == pytest.approx(15.0)
    assert s["network_ms"] == pytest.approx(21.0) and s["bytes_down"] == 1000
    # the pipeline is slower than the 20 ms period: frame 1 starts when frame 0 is displayed
    assert frames[1].start_s == pytest.approx(41 * MS)
    assert frames[1].display_s == pytest.approx(82 * MS)
    assert frames[1].frame_interval_ms == pytest.approx(41.0)


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


def _async_schedule(max_in_flight, n_frames):
    # client: 4 ms per frame every 10 ms; server update: 25 ms of work, then a message with 10 ms delay
    tl = Timeline(_links(delay_ms=10.0))

    def update(g, input_s):
        g.add_stage("render", "server", 25 * MS)
        g.add_message("layers", 0, "down")
        return input_s

    def frame(g, u):
        g.add_stage("warp", "client", 4 * MS)

    return run_async(tl, n_frames, 10 * MS, update, frame, max_in_flight=max_in_flight)


def test04_async_client_uses_newest_update_that_has_arrived():
    frames, updates = _async_schedule(max_in_flight=1, n_frames=8)
    # updates: u0 starts 0 -> arrives 35 ms; u1 starts at 35 (input snapped to the 30 ms frame) -> 70; u2 at 70
    assert [u.start_s / MS for u in updates] == pytest.approx([0, 35, 70])
    assert [u.input_s / MS for u in updates] == pytest.approx([0, 30, 70])
    assert [u.arrival_s / MS for u in updates] == pytest.approx([35, 70, 105])
    assert [f.update_index for f in frames] == [-1, -1, -1, -1, 0, 0, 0, 1]
    assert all(f.frame_ms == pytest.approx(4.0) and f.latency_ms == pytest.approx(4.0) for f in frames)
    # staleness = display - input of the update used: 44 - 0, 54 - 0, 64 - 0, 74 - 30
    assert [f.staleness_ms for f in frames[4:]] == pytest.approx([44, 54, 64, 44])
    assert math.isnan(frames[0].staleness_ms)


def test05_pipelined_updates_overlap_compute_with_transfer():
    frames, updates = _async_schedule(max_in_flight=2, n_frames=10)
    # u1 starts when the server is free (25 ms), not when u0 arrives (35 ms); u2 waits for u0's arrival and
    # the server (50 ms); u3 for u1's arrival (60) and the server (75)
    assert [u.start_s / MS for u in updates] == pytest.approx([0, 25, 50, 75])
    assert [u.input_s / MS for u in updates] == pytest.approx([0, 20, 50, 70])
    assert [u.arrival_s / MS for u in updates] == pytest.approx([35, 60, 85, 110])
    assert [f.update_index for f in frames] == [-1, -1, -1, -1, 0, 0, 1, 1, 1, 2]
    assert [f.staleness_ms for f in frames[4:]] == pytest.approx([44, 54, 44, 54, 64, 44])


def test06_lockstep_zero_latency_frame_uses_an_update_made_for_its_own_time():
    tl = Timeline()  # ideal links
    frames, updates = run_async(tl, 2, 10 * MS,
                                lambda g, t: g.add_stage("render", "server", 25 * MS),
                                lambda g, u: g.add_stage("warp", "client", 4 * MS), lockstep=True)
    assert [f.update_index for f in frames] == [0, 1]
    assert [u.start_s / MS for u in updates] == pytest.approx([0, 29])
    assert [f.latency_ms for f in frames] == pytest.approx([29, 29])
    assert [f.staleness_ms for f in frames] == pytest.approx([29, 29])


def test07_sends_out_of_time_order_queue_behind_earlier_ones():
    tl = Timeline(_links(delay_ms=0.0))
    g = tl.group("frame", 0, 0.0)
    g.add_stage("slow", "server", 10 * MS, after=[])
    g.add_message("late", 10, "down", after=["slow"])
    g.add_stage("fast", "client", 1 * MS, after=[])
    early = g.add_message("early", 10, "down", after=["fast"])[0]
    assert early.start_s == pytest.approx(10 * MS)
    assert tl.reordered_sends == 1


def test08_a_message_that_never_arrives_releases_dependants_after_the_timeout():
    class Blackhole:
        def send(self, size_bytes, direction, protocol, at_s, deadline_s=None):
            from suite.harness.timeline import Delivery
            return Delivery(arrival_s=math.inf, delivered_bytes=0, lost_ranges=[(0, size_bytes)], complete=False)

    tl = Timeline({"down": Blackhole(), "up": Blackhole()}, message_timeout_s=0.1)
    g = tl.group("frame", 0, 0.0)
    ev, _ = g.add_message("m", 100, "down", protocol="udp")
    after = g.add_stage("use", "client", 1 * MS)
    assert not ev.complete and ev.lost_bytes == 100
    assert after.start_s == pytest.approx(0.1)


def test08b_udp_data_arriving_after_the_timeout_counts_as_lost():
    """The receiver stops waiting for a UDP message at the timeout: later datagrams are lost to the method."""
    import netsim

    # 100 kB at 1 Mbit/s takes 0.8 s; the receiver waits 0.1 s.
    links = {"down": netsim.make_network("bw=1mbps,delay=5ms", seed=0),
             "up": netsim.make_network("bw=1mbps,delay=5ms", seed=0)}
    tl = Timeline(links, message_timeout_s=0.1)
    g = tl.group("frame", 0, 0.0)
    ev, d = g.add_message("m", 100_000, "down", protocol="udp")
    assert not ev.complete
    assert 0 < ev.delivered_bytes < 0.15 * 100_000  # only what arrived within 100 ms (about 11.9 kB)
    assert ev.end_s <= 0.1 + 1e-9
    assert sum(end - start for start, end in d.lost_ranges) == 100_000 - ev.delivered_bytes


from hypothesis import given, settings
from hypothesis import strategies as st

_stages = st.lists(st.tuples(st.sampled_from(["client", "server"]), st.integers(0, 50)), min_size=1, max_size=8)


@settings(max_examples=60, deadline=None)
@given(_stages)
def test09_a_chain_takes_the_sum_and_independent_stages_the_busier_place(stages):
    chain = Timeline().group("frame", 0, 0.0)
    for k, (place, ms) in enumerate(stages):
        chain.add_stage(f"s{k}", place, ms * MS)
    assert chain.end_s == pytest.approx(sum(ms for _, ms in stages) * MS)

    parallel = Timeline().group("frame", 0, 0.0)
    for k, (place, ms) in enumerate(stages):
        parallel.add_stage(f"s{k}", place, ms * MS, after=[])
    busiest_ms = max(sum(ms for p, ms in stages if p == place) for place in ("client", "server"))
    assert parallel.end_s == pytest.approx(busiest_ms * MS)


def test10_updates_never_repeat_an_input_even_when_they_cost_nothing():
    tl = Timeline()  # ideal links: a message-only update takes zero time
    frames, updates = run_async(tl, 3, 10 * MS, lambda g, t: g.add_message("m", 10, "down"),
                                lambda g, u: g.add_stage("warp", "client", 1 * MS), max_in_flight=4)
    assert [u.input_s / MS for u in updates] == pytest.approx([0, 10, 20])
    assert [f.update_index for f in frames] == [0, 1, 2]
