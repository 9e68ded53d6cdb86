"""TCP: slow start, loss recovery, RTO, slow-start restart, head-of-line blocking, shared connection."""

import math

import pytest

import netsim
from netsim.config import LinkConfig, TcpConfig
from netsim.env import Environment
from netsim.link import Link
from netsim.tcp import Message, TcpConnection, _CongestionState

MSS = 1460
# A path with negligible serialisation (1 Tbit/s) so that timings are whole round trips.
FAST_PATH = "bw=1000000mbps,delay=10ms"


@pytest.mark.parametrize("segments, rounds", [(10, 1), (11, 2), (30, 2), (31, 3), (70, 3), (150, 4)])
def test_slow_start_doubles_the_window_each_round_trip(segments, rounds):
    # IW = 10 segments (RFC 6928) and +1 segment per ACK: rounds carry 10, 20, 40, 80 ... segments, so the last
    # byte arrives (rounds - 1) round trips + one one-way delay after the send.
    net = netsim.make_network(FAST_PATH, seed=0)
    delivery = net.send(segments * MSS, protocol="tcp", at_s=0.0)
    expected_s = (rounds - 1) * 0.020 + 0.010
    assert delivery.arrival_s == pytest.approx(expected_s, abs=1e-4)


def test_counted_handshake_adds_one_round_trip_to_the_first_message_only():
    net = netsim.make_network(FAST_PATH + ",handshake=on", seed=0)
    first = net.send(1000, at_s=0.0)
    second = net.send(1000, at_s=1.0)
    assert first.arrival_s == pytest.approx(0.030, abs=1e-4)
    assert second.arrival_s - 1.0 == pytest.approx(0.010, abs=1e-4)


def _single_connection(spec_link: dict, tcp: TcpConfig = TcpConfig()):
    env = Environment(seed=0)
    link = Link(env, LinkConfig(**spec_link), "down")
    connection = TcpConnection(env, link, reverse_delay_s=link.delay_s, config=tcp)
    return link, connection


def test_a_single_loss_is_repaired_by_fast_retransmit_within_about_one_round_trip():
    size = 1_000_000
    _, clean = _single_connection({"bandwidth_mbps": 10, "delay_ms": 10})
    clean_arrival = clean.put(Message(size_bytes=size, at_s=0.0)).arrival_s
    link, lossy = _single_connection({"bandwidth_mbps": 10, "delay_ms": 10})
    link.scripted_losses = {50}
    message = lossy.put(Message(size_bytes=size, at_s=0.0))
    assert message.complete and message.delivered_bytes == size
    assert message.retransmissions == 1
    assert lossy.fast_retransmits == 1 and lossy.timeouts == 0
    assert clean_arrival < message.arrival_s <= clean_arrival + 0.020 + 0.002


@pytest.mark.parametrize("sack", [True, False])
def test_random_loss_is_recovered_and_every_byte_delivered(sack):
    net = netsim.make_network(f"bw=20mbps,delay=15ms,loss=2%,sack={'on' if sack else 'off'}", seed=3)
    delivery = net.send(2_000_000, at_s=0.0)
    assert delivery.complete
    assert delivery.delivered_bytes == 2_000_000 and delivery.lost_ranges == []
    assert delivery.retransmissions >= net.links["down"].packets_lost > 0


def test_a_lost_last_segment_waits_for_the_200_ms_minimum_rto():
    # 2 ms RTT: RFC 6298 would give an RTO of a few ms; the 200 ms floor (Linux) applies.
    link, connection = _single_connection({"bandwidth_mbps": 100, "delay_ms": 1})
    link.scripted_losses = {0}
    message = connection.put(Message(size_bytes=1000, at_s=0.0))
    assert connection.timeouts == 1 and message.retransmissions == 1
    assert 0.200 <= message.arrival_s <= 0.200 + 0.001 + 0.0005


def test_the_minimum_rto_is_configurable():
    link, connection = _single_connection({"bandwidth_mbps": 100, "delay_ms": 1}, TcpConfig(min_rto_ms=300))
    link.scripted_losses = {0}
    message = connection.put(Message(size_bytes=1000, at_s=0.0))
    assert 0.300 <= message.arrival_s <= 0.302


def test_rto_backs_off_exponentially_when_the_retransmission_is_lost_too():
    link, connection = _single_connection({"bandwidth_mbps": 100, "delay_ms": 1})
    link.scripted_losses = {0, 1}
    message = connection.put(Message(size_bytes=1000, at_s=0.0))
    assert connection.timeouts == 2
    assert message.arrival_s == pytest.approx(0.200 + 0.400 + 0.001, abs=0.001)


def _durations(spec: str, idle_s: float) -> tuple[float, float]:
    net = netsim.make_network(spec, seed=0)
    first = net.send(1_000_000, at_s=0.0)
    start = first.arrival_s + idle_s
    second = net.send(1_000_000, at_s=start)
    return first.arrival_s, second.arrival_s - start


def test_slow_start_restarts_after_an_idle_period_longer_than_the_rto():
    first_s, second_s = _durations("bw=100mbps,delay=10ms", idle_s=5.0)
    assert second_s == pytest.approx(first_s, rel=0.01)  # back to IW: the same ramp as a fresh connection


def test_without_slow_start_restart_a_warm_connection_is_faster():
    first_s, second_s = _durations("bw=100mbps,delay=10ms,ssr=off", idle_s=5.0)
    assert second_s < 0.8 * first_s


def test_a_short_idle_period_keeps_the_window():
    first_s, second_s = _durations("bw=100mbps,delay=10ms", idle_s=0.05)  # 50 ms < RTO (200 ms)
    assert second_s < 0.8 * first_s


def test_head_of_line_blocking_a_small_message_waits_behind_a_large_one():
    net = netsim.make_network("bw=20mbps,delay=10ms", seed=0)
    large = net.send(1_000_000, at_s=0.0)
    small = net.send(100, at_s=0.001)
    assert small.arrival_s >= large.arrival_s


def test_head_of_line_blocking_a_loss_in_the_earlier_message_delays_the_later_one():
    net = netsim.make_network("bw=20mbps,delay=10ms", seed=0)
    net.links["down"].scripted_losses = {60}  # a segment of the first message near its end
    first = net.send(100_000, at_s=0.0)
    second = net.send(1000, at_s=0.0)
    assert first.retransmissions == 1
    assert second.arrival_s >= first.arrival_s


def test_messages_on_one_connection_share_it_like_one_stream():
    alone = netsim.make_network("bw=20mbps,delay=10ms", seed=0).send(2_000_000, at_s=0.0)
    net = netsim.make_network("bw=20mbps,delay=10ms", seed=0)
    first = net.send(1_000_000, at_s=0.0)
    second = net.send(1_000_000, at_s=0.0005)
    assert second.arrival_s == pytest.approx(alone.arrival_s, rel=0.02)
    assert first.arrival_s < second.arrival_s


def test_an_overlapping_message_updates_the_earlier_delivery_in_place():
    net = netsim.make_network("bw=20mbps,delay=10ms", seed=0)
    net.links["down"].scripted_losses = {68}  # the last segment of the first message: a tail loss
    first = net.send(100_000, at_s=0.0)
    alone_arrival = first.arrival_s  # repaired by the RTO (no later segments to trigger duplicate ACKs)
    net.send(200_000, at_s=0.001)    # later segments bring duplicate ACKs: fast retransmit instead
    assert first.arrival_s < alone_arrival - 0.1


def test_delayed_acks_slow_the_slow_start_ramp():
    quick = netsim.make_network(FAST_PATH, seed=0).send(150 * MSS, at_s=0.0)
    delayed = netsim.make_network(FAST_PATH + ",delack=on", seed=0).send(150 * MSS, at_s=0.0)
    assert delayed.complete and delayed.arrival_s > quick.arrival_s


def test_the_receive_window_caps_throughput():
    # 64 kB window over a 100 ms RTT: at most ~5.2 Mbit/s whatever the link rate.
    net = netsim.make_network("bw=100mbps,delay=50ms,rwnd=64kb", seed=0)
    delivery = net.send(2_000_000, at_s=0.0)
    goodput_mbps = 2_000_000 * 8 / delivery.arrival_s / 1e6
    assert goodput_mbps < 64_000 * 8 / 0.100 / 1e6 * 1.05


@pytest.mark.parametrize("cc", ["newreno", "cubic"])
def test_both_congestion_controls_fill_a_clean_pipe(cc):
    net = netsim.make_network(f"bw=50mbps,delay=17ms,cc={cc}", seed=0)
    delivery = net.send(8_000_000, at_s=0.0)
    serialisation_s = 8_000_000 * 1500 / 1460 * 8 / 50e6
    assert serialisation_s + 0.017 < delivery.arrival_s < (serialisation_s + 0.017) * 1.15


def test_newreno_halves_the_flight_on_loss():
    state = _CongestionState(TcpConfig(congestion_control="newreno"))
    state.cwnd, state.ssthresh = 100.0, 50.0
    state.on_loss(flight_segments=100)
    assert state.ssthresh == 50.0  # RFC 5681 eq. (4)


def test_cubic_backs_off_by_beta_and_regrows_to_w_max_after_k_seconds():
    state = _CongestionState(TcpConfig(congestion_control="cubic"))
    state.cwnd, state.ssthresh = 100.0, 50.0
    state.on_loss(flight_segments=100)
    assert state.ssthresh == pytest.approx(70.0)  # beta = 0.7 (RFC 9438 4.6)
    state.cwnd = state.ssthresh
    k_s = (100.0 * (1 - 0.7) / 0.4) ** (1 / 3)  # RFC 9438 eq. (2)
    rtt_s = 0.5  # long enough that the Reno-friendly estimate (RFC 9438 4.3) stays below the cubic curve
    t = 0.0
    while t < k_s - rtt_s:  # one window of ACKs per round trip
        for _ in range(int(state.cwnd)):
            state.on_ack(1, t, rtt_s)
        t += rtt_s
    assert state.cwnd == pytest.approx(100.0, rel=0.05)


def test_a_transfer_that_cannot_finish_stops_at_the_time_cap():
    net = netsim.make_network({"bw": 10, "delay": 10, "loss": 0.95, "max_sim_time_s": 5.0}, seed=0)
    delivery = net.send(100_000, at_s=0.0)
    assert not delivery.complete and math.isinf(delivery.arrival_s)
    assert delivery.delivered_bytes < 100_000
    assert delivery.lost_ranges == [(delivery.delivered_bytes, 100_000)]
