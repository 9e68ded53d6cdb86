"""UDP: exact lost byte ranges, FEC, NACK rounds, deadlines, pacing."""

import math

import pytest

import netsim
from netsim.config import LinkConfig, UdpConfig
from netsim.env import Environment
from netsim.link import Link
from netsim.tcp import Message
from netsim.udp import UdpSender

PAYLOAD = 1500 - 28  # bytes of message per datagram at MTU 1500


def _sender(udp: UdpConfig = UdpConfig(), scripted=(), **link):
    env = Environment(seed=0)
    settings = {"bandwidth_mbps": 10, "delay_ms": 5}
    settings.update(link)
    down = Link(env, LinkConfig(**settings), "down")
    down.scripted_losses = set(scripted)
    return UdpSender(env, down, reverse_delay_s=0.005, config=udp)


def test_lost_ranges_are_exactly_the_bytes_of_the_lost_datagrams():
    size = 20 * PAYLOAD + 100
    message = _sender(scripted={2, 3, 7, 20}).put(Message(size_bytes=size, at_s=0.0))
    assert message.lost_ranges == [(2 * PAYLOAD, 4 * PAYLOAD), (7 * PAYLOAD, 8 * PAYLOAD), (20 * PAYLOAD, size)]
    assert message.delivered_bytes == size - 3 * PAYLOAD - 100
    assert not message.complete and math.isinf(message.arrival_s)


def test_lost_ranges_and_delivered_bytes_always_add_up_to_the_message():
    net = netsim.make_network("bw=20mbps,delay=5ms,loss=5%", seed=11)
    for at_s in (0.0, 0.5, 1.0):
        delivery = net.send(300_000, protocol="udp", at_s=at_s)
        lost = sum(end - start for start, end in delivery.lost_ranges)
        assert lost + delivery.delivered_bytes == 300_000
        starts = [start for start, _ in delivery.lost_ranges]
        assert starts == sorted(starts) and all(start % PAYLOAD == 0 for start in starts)
        assert all(a_end < b_start for (_, a_end), (b_start, _) in zip(delivery.lost_ranges,
                                                                       delivery.lost_ranges[1:]))


def test_lost_ranges_are_deterministic_for_a_seed_and_change_with_it():
    def ranges(seed):
        net = netsim.make_network("bw=20mbps,delay=5ms,loss=5%", seed=seed)
        return [net.send(200_000, protocol="udp", at_s=0.1 * i).lost_ranges for i in range(3)]

    assert ranges(4) == ranges(4)
    assert ranges(4) != ranges(5)


def test_a_complete_message_arrives_when_its_last_datagram_does():
    sender = _sender()
    message = sender.put(Message(size_bytes=10 * PAYLOAD, at_s=0.0))
    # Burst: the link serialises 10 datagrams of 1500 bytes at 10 Mbit/s, then 5 ms of propagation.
    assert message.complete and message.arrival_s == pytest.approx(10 * 1500 * 8 / 10e6 + 0.005)


def test_a_burst_overflows_a_small_queue_but_default_pacing_does_not():
    burst = _sender(UdpConfig(burst=True), queue_bytes=20 * 1500).put(Message(size_bytes=50 * PAYLOAD, at_s=0.0))
    paced = _sender(queue_bytes=20 * 1500).put(Message(size_bytes=50 * PAYLOAD, at_s=0.0))
    assert burst.delivered_bytes == 21 * PAYLOAD and burst.lost_ranges == [(21 * PAYLOAD, 50 * PAYLOAD)]
    assert paced.complete and paced.arrival_s == pytest.approx(50 * 1500 * 8 / 10e6 + 0.005)


def test_pacing_spreads_datagrams_at_the_stated_rate():
    sender = _sender(UdpConfig(pacing_mbps=1.0))
    message = sender.put(Message(size_bytes=10 * PAYLOAD, at_s=0.0))
    # The 10th datagram leaves 9 gaps of 12 ms after the first.
    assert message.arrival_s == pytest.approx(9 * 1500 * 8 / 1e6 + 1500 * 8 / 10e6 + 0.005)


@pytest.mark.parametrize("lost_in_block", [[0], [0, 1], [1, 4], [4, 5]])
def test_fec_recovers_up_to_r_losses_per_block(lost_in_block):
    # k = 4 data + r = 2 parity: offers 0-3 are data, 4-5 parity, 6-9 data of block 1, ...
    sender = _sender(UdpConfig(fec_k=4, fec_r=2), scripted=lost_in_block)
    message = sender.put(Message(size_bytes=8 * PAYLOAD, at_s=0.0))
    assert message.complete and message.lost_ranges == []
    assert sender.parity_sent == 4


def test_fec_cannot_recover_more_than_r_losses_in_a_block():
    sender = _sender(UdpConfig(fec_k=4, fec_r=2), scripted=[0, 1, 2])
    message = sender.put(Message(size_bytes=8 * PAYLOAD, at_s=0.0))
    assert message.lost_ranges == [(0, 3 * PAYLOAD)]


def test_fec_costs_r_over_k_extra_bandwidth():
    plain = _sender()
    plain.put(Message(size_bytes=40 * PAYLOAD, at_s=0.0))
    coded = _sender(UdpConfig(fec_k=8, fec_r=2))
    coded.put(Message(size_bytes=40 * PAYLOAD, at_s=0.0))
    assert coded.link.bytes_sent == pytest.approx(plain.link.bytes_sent * 10 / 8)


def test_nack_rounds_resend_the_missing_datagrams():
    sender = _sender(UdpConfig(nack_rounds=1), scripted=[3])
    message = sender.put(Message(size_bytes=10 * PAYLOAD, at_s=0.0))
    assert message.complete and message.retransmissions == 1
    first_pass_end_s = 10 * 1500 * 8 / 10e6 + 0.005
    # The report leaves at the end of the pass, takes 5 ms back, and the resend 5 ms + 1.2 ms forward.
    assert message.arrival_s == pytest.approx(first_pass_end_s + 0.005 + 1500 * 8 / 10e6 + 0.005)


def test_without_nack_nothing_is_retransmitted():
    sender = _sender(scripted=[3])
    message = sender.put(Message(size_bytes=10 * PAYLOAD, at_s=0.0))
    assert message.retransmissions == 0 and message.lost_ranges == [(3 * PAYLOAD, 4 * PAYLOAD)]


def test_data_after_the_deadline_counts_as_lost():
    net = netsim.make_network("bw=10mbps,delay=5ms", seed=0)
    # 1 MB takes ~0.82 s at 10 Mbit/s; with a 0.3 s budget only the first ~245 kB make it.
    delivery = net.send(1_000_000, protocol="udp", at_s=0.0, deadline_s=0.3)
    assert not delivery.complete and math.isinf(delivery.arrival_s)
    assert len(delivery.lost_ranges) == 1
    start, end = delivery.lost_ranges[0]
    assert end == 1_000_000 and start == delivery.delivered_bytes and start % PAYLOAD == 0
    datagrams_in_time = int((0.3 - 0.005) / (1500 * 8 / 10e6))
    assert delivery.delivered_bytes == datagrams_in_time * PAYLOAD
    assert delivery.settled_s <= 0.3


def test_a_deadline_that_is_met_changes_nothing():
    net = netsim.make_network("bw=10mbps,delay=5ms", seed=0)
    delivery = net.send(10_000, protocol="udp", at_s=0.0, deadline_s=1.0)
    assert delivery.complete and delivery.lost_ranges == []


def test_a_tcp_message_later_than_its_deadline_is_incomplete():
    net = netsim.make_network("bw=10mbps,delay=5ms", seed=0)
    delivery = net.send(1_000_000, protocol="tcp", at_s=0.0, deadline_s=0.3)
    assert not delivery.complete and 0 < delivery.delivered_bytes < 1_000_000
    assert delivery.lost_ranges == [(delivery.delivered_bytes, 1_000_000)]


def test_concurrent_udp_messages_queue_behind_each_other_on_the_link():
    net = netsim.make_network("bw=10mbps,delay=5ms", seed=0)
    first = net.send(100 * PAYLOAD, protocol="udp", at_s=0.0)
    second = net.send(100 * PAYLOAD, protocol="udp", at_s=0.0)
    one_message_s = 100 * 1500 * 8 / 10e6
    assert first.arrival_s == pytest.approx(one_message_s + 0.005)
    assert second.arrival_s == pytest.approx(2 * one_message_s + 0.005)
