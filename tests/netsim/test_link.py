"""Link: serialisation, propagation, drop-tail queue, Bernoulli and Gilbert-Elliott loss, jitter, traces."""

import pytest

from netsim.config import LinkConfig
from netsim.env import Environment
from netsim.link import Link, Packet
from netsim.traces import parse_mahimahi


def _link(**settings) -> Link:
    return Link(Environment(seed=0), LinkConfig(**settings), "down")


def test_a_packet_arrives_after_serialisation_plus_propagation():
    link = _link(bandwidth_mbps=10, delay_ms=5)
    packet = link.put(Packet(size_bytes=1500, sent_s=1.0))
    assert packet.arrival_s == pytest.approx(1.0 + 1500 * 8 / 10e6 + 0.005)
    assert link.out == [packet] and link.packets_sent == 1 and link.bytes_sent == 1500


def test_back_to_back_packets_leave_one_serialisation_time_apart():
    link = _link(bandwidth_mbps=10, delay_ms=5)
    arrivals = [link.transmit(0.0, 1500) for _ in range(5)]
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    assert gaps == pytest.approx([1500 * 8 / 10e6] * 4)


def test_drop_tail_queue_drops_what_does_not_fit():
    link = _link(bandwidth_mbps=10, delay_ms=5, queue_bytes=10 * 1500)
    arrivals = [link.transmit(0.0, 1500) for _ in range(20)]
    # The first packet goes straight to the wire; ten more wait in the queue; the rest are dropped.
    assert sum(a is not None for a in arrivals) == 11
    assert link.packets_dropped_queue == 9
    assert all(a is None for a in arrivals[11:])


def test_bernoulli_loss_rate_matches_the_setting():
    link = _link(bandwidth_mbps=1000, delay_ms=1, loss=0.1)
    lost = sum(link.transmit(i * 1e-3, 1500) is None for i in range(20_000))
    assert lost / 20_000 == pytest.approx(0.1, abs=0.01)


def test_gilbert_elliott_losses_come_in_bursts_at_the_stationary_rate():
    # p = 1 %, r = 25 %: pi_bad = 0.01 / 0.26 = 3.8 %, mean burst = 1 / r = 4 packets.
    link = _link(bandwidth_mbps=1000, delay_ms=1, ge_p=0.01, ge_r=0.25, ge_loss_bad=1.0)
    outcomes = [link.transmit(i * 1e-3, 1500) is None for i in range(50_000)]
    rate = sum(outcomes) / len(outcomes)
    assert rate == pytest.approx(0.01 / 0.26, rel=0.15)
    bursts = sum(1 for a, b in zip(outcomes, outcomes[1:]) if b and not a)
    assert sum(outcomes) / bursts == pytest.approx(4.0, rel=0.2)


def test_jitter_delays_packets_but_never_reorders_them_by_default():
    link = _link(bandwidth_mbps=100, delay_ms=10, jitter_ms=5, jitter_distribution="exponential")
    arrivals = [link.transmit(i * 1e-4, 1500) for i in range(2000)]
    assert arrivals == sorted(arrivals)
    assert min(a - i * 1e-4 for i, a in enumerate(arrivals)) >= 0.010


@pytest.mark.parametrize("distribution", ["uniform", "exponential", "normal"])
def test_jitter_has_the_stated_scale(distribution):
    link = _link(bandwidth_mbps=1000, delay_ms=10, jitter_ms=2, jitter_distribution=distribution, reorder=True)
    extra_ms = [(link.transmit(i * 0.1, 100) - i * 0.1 - 0.010 - 100 * 8 / 1e9) * 1e3 for i in range(4000)]
    assert min(extra_ms) >= -1e-9  # never early (up to float rounding)
    mean_ms = sum(extra_ms) / len(extra_ms)
    expected_ms = {"uniform": 2.0, "exponential": 2.0, "normal": 2.0 * 0.3989}[distribution]
    assert mean_ms == pytest.approx(expected_ms, rel=0.1)


def test_reordering_happens_only_when_asked():
    link = _link(bandwidth_mbps=1000, delay_ms=10, jitter_ms=5, jitter_distribution="uniform", reorder=True)
    arrivals = [link.transmit(i * 1e-5, 100) for i in range(500)]
    assert arrivals != sorted(arrivals)


def test_same_seed_same_losses():
    def pattern(seed):
        link = Link(Environment(seed=seed), LinkConfig(bandwidth_mbps=100, loss=0.2), "down")
        return [link.transmit(i * 1e-3, 1500) is None for i in range(200)]

    assert pattern(1) == pattern(1)
    assert pattern(1) != pattern(2)


def test_a_trace_link_serves_one_1500_byte_packet_per_opportunity(tmp_path):
    trace = tmp_path / "one-per-ms.mahi"
    trace.write_text("\n".join(str(ms) for ms in range(1, 101)) + "\n")
    link = _link(delay_ms=0, trace_path=str(trace))
    departures = [link.transmit(0.0, 1500) for _ in range(150)]
    assert departures[0] == pytest.approx(0.001)
    assert departures[99] == pytest.approx(0.100)
    assert departures[149] == pytest.approx(0.150)  # the trace loops with a 100 ms period


def test_small_packets_share_an_opportunity_on_a_trace_link(tmp_path):
    trace = tmp_path / "t.mahi"
    trace.write_text("5\n10\n")
    link = _link(delay_ms=0, trace_path=str(trace))
    departures = [link.transmit(0.0, 500) for _ in range(4)]
    assert departures == pytest.approx([0.005, 0.005, 0.005, 0.010])


def test_unused_trace_opportunities_are_lost(tmp_path):
    trace = tmp_path / "t.mahi"
    trace.write_text("\n".join(str(ms) for ms in range(1, 11)) + "\n")
    link = _link(delay_ms=0, trace_path=str(trace))
    assert link.transmit(0.0, 1500) == pytest.approx(0.001)
    assert link.transmit(0.0045, 1500) == pytest.approx(0.005)


def test_mahimahi_parsing_reads_timestamps_and_rejects_bad_lines():
    assert list(parse_mahimahi("1\n1\n3\n\n5\n")) == [1, 1, 3, 5]
    from netsim.errors import NetsimError

    for text, message in [("", "empty"), ("1\nx\n", "line 2"), ("3\n2\n", "non-decreasing"), ("0\n", "> 0")]:
        with pytest.raises(NetsimError, match=message):
            parse_mahimahi(text)
