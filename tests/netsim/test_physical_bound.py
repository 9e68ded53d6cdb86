"""No message ever arrives earlier than one-way delay + serialisation of its bytes and headers at link rate."""

import math

from hypothesis import given, settings, strategies as st

import netsim


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    bandwidth_mbps=st.floats(min_value=1.0, max_value=1000.0),
    delay_ms=st.floats(min_value=0.0, max_value=100.0),
    jitter_ms=st.floats(min_value=0.0, max_value=5.0),
    loss=st.sampled_from([0.0, 0.001, 0.01, 0.05]),
    sizes_bytes=st.lists(st.integers(min_value=1, max_value=400_000), min_size=1, max_size=4),
    gaps_s=st.lists(st.floats(min_value=0.0, max_value=0.5), min_size=4, max_size=4),
    protocol=st.sampled_from(["tcp", "udp"]),
    mtu_bytes=st.sampled_from([576, 1500, 9000]),
    seed=st.integers(min_value=0, max_value=3),
)
def test_no_message_beats_propagation_plus_serialisation(bandwidth_mbps, delay_ms, jitter_ms, loss, sizes_bytes,
                                                         gaps_s, protocol, mtu_bytes, seed):
    net = netsim.make_network({"bw": bandwidth_mbps, "delay": delay_ms, "jitter": jitter_ms, "loss": loss,
                               "mtu": mtu_bytes}, seed=seed)
    header_bytes = 40 if protocol == "tcp" else 28
    payload_bytes = mtu_bytes - header_bytes
    at_s = 0.0
    for size_bytes, gap_s in zip(sizes_bytes, gaps_s):
        at_s += gap_s
        delivery = net.send(size_bytes, direction="down", protocol=protocol, at_s=at_s)
        if not delivery.complete:
            assert math.isinf(delivery.arrival_s)
            continue
        wire_bytes = size_bytes + math.ceil(size_bytes / payload_bytes) * header_bytes
        bound_s = at_s + delay_ms * 1e-3 + wire_bytes * 8 / (bandwidth_mbps * 1e6)
        assert delivery.arrival_s >= bound_s - 1e-12
