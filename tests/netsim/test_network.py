"""The harness-facing Network: determinism, directions, metadata."""

import json

import netsim


def _run(seed: int):
    net = netsim.make_network("wifi-40m,loss=2%", seed=seed)
    results = []
    at_s = 0.0
    for index in range(12):
        protocol = "tcp" if index % 3 else "udp"
        direction = "up" if index % 4 == 0 else "down"
        results.append(net.send(50_000 + 7_000 * index, direction=direction, protocol=protocol, at_s=at_s))
        at_s += 0.03
    return [d.to_dict() for d in results]


def test_the_same_seed_gives_identical_results():
    assert _run(3) == _run(3)


def test_a_different_seed_gives_different_losses():
    assert _run(3) != _run(4)


def test_directions_use_their_own_links():
    net = netsim.make_network("dsl-3m", seed=0)
    down = net.send(100_000, direction="down", at_s=0.0)
    up = net.send(100_000, direction="up", at_s=0.0)
    # dsl-3m: 3 Mbit/s down, 0.5 Mbit/s up.
    assert up.arrival_s > 4 * down.arrival_s


def test_delivery_fields_are_filled_in():
    delivery = netsim.make_network("wan-50m", seed=0).send(300_000, at_s=1.0)
    assert delivery.sent_s == 1.0 and delivery.size_bytes == 300_000
    assert delivery.complete and delivery.delivered_bytes == 300_000 and delivery.lost_ranges == []
    assert delivery.retransmissions == 0 and delivery.arrival_s > 1.017
    json.dumps(delivery.to_dict())


def test_describe_is_json_and_names_the_seed():
    description = netsim.make_network("bw=50mbps,delay=17ms,loss=0.1%", seed=5).describe()
    assert json.loads(json.dumps(description))["seed"] == 5
    assert description["down"]["bandwidth_mbps"] == 50


def test_a_small_message_does_not_wait_for_the_previous_ones_ack():
    # A 64-byte pose every 10 ms over a 10 ms path: with TCP_NODELAY each one leaves when it is written (the
    # window has room), so every pose arrives one propagation delay plus serialisation later, not after the
    # previous pose's ACK. The single-path engine and the topology engine agree.
    net = netsim.make_network("bw=50mbps,delay=10ms", seed=0)
    single = [net.send(64, direction="up", protocol="tcp", at_s=0.010 * i) for i in range(8)]
    topo = netsim.make_topology(access="bw=50mbps,delay=10ms", server="bw=10gbps,delay=0ms", clients=1, seed=0)
    joint = []
    for i in range(8):
        joint.append(topo.send(64, client=0, direction="up", protocol="tcp", at_s=0.010 * i))
        topo.advance(0.010 * i)
    topo.advance(1.0)
    for d in single + joint:
        assert 10.0 <= 1e3 * (d.arrival_s - d.sent_s) < 11.5
