"""Topologies: C clients, each behind its own access link, sharing the server's link.

The API, bad input, sharing one drop-tail queue (two and eight TCP flows, TCP with UDP, up and down), the serial
composition of two links, and the guarantees: determinism, independence of the submission order, causality.
"""

import json
import math
import random

import pytest

import netsim
from netsim import link as link_module
from netsim.topology import derive_seed

MSS = 1460
WIRE_PER_PAYLOAD = 1500 / 1460  # IP + TCP headers on full segments


def _record(delivery):
    return (delivery.arrival_s, delivery.settled_s, delivery.delivered_bytes, tuple(delivery.lost_ranges),
            delivery.retransmissions, delivery.complete)


# -- the API ------------------------------------------------------------------------------------------------------
def test_make_topology_send_advance_describe_counters():
    topo = netsim.make_topology(access="lan-home", server="bw=100mbps,delay=5ms,queue=1000p", clients=3, seed=0)
    d = topo.send(100_000, client=1, direction="down", protocol="tcp", at_s=0.25, deadline_s=None)
    assert isinstance(d, netsim.Delivery)
    assert d.complete and d.delivered_bytes == 100_000 and d.lost_ranges == [] and d.sent_s == 0.25
    assert d.arrival_s > 0.25 + 0.0075 and d.settled_s == d.arrival_s
    topo.advance(0.5)
    up = topo.send(2_000, client=2, direction="up", protocol="udp", at_s=0.5)
    assert up.complete
    description = json.loads(json.dumps(topo.describe()))
    assert description["clients"] == 3 and description["seed"] == 0
    assert description["access"]["name"] == "lan-home" and description["server"]["down"]["bandwidth_mbps"] == 100
    counters = topo.counters()
    assert counters["server"]["down"]["packets_sent"] == counters["clients"][1]["down"]["packets_sent"] > 68
    assert counters["clients"][2]["up"]["udp_datagrams_sent"] == 2
    assert counters["clients"][0]["down"]["packets_sent"] == 0
    json.dumps(counters)


def test_netsim_exports_the_topology_api():
    for name in ("make_topology", "Topology", "NetsimError", "derive_seed"):
        assert name in netsim.__all__ and getattr(netsim, name)


def test_without_a_server_link_each_client_direction_is_todays_network_with_derived_seeds():
    # server=None: client i's two directions are independent Networks seeded derive_seed(seed, i, d); client 0
    # keeps the harness's historical seeds 2 * seed (down) and 2 * seed + 1 (up).
    assert derive_seed(7, 0, "down") == 14 and derive_seed(7, 0, "up") == 15
    seeds = {derive_seed(7, i, d) for i in range(50) for d in ("down", "up")}
    assert len(seeds) == 100  # distinct loss streams
    spec = "wifi-40m,loss=2%"
    topo = netsim.make_topology(access=spec, server=None, clients=2, seed=7)
    nets = {(i, d): netsim.make_network(spec, seed=derive_seed(7, i, d)) for i in range(2) for d in ("down", "up")}
    at_s = 0.0
    for k in range(16):
        client, direction = k % 2, ("down", "up")[(k // 2) % 2]
        protocol = "udp" if k % 3 == 0 else "tcp"
        size = 40_000 + 9_000 * k
        got = topo.send(size, client=client, direction=direction, protocol=protocol, at_s=at_s)
        want = nets[(client, direction)].send(size, direction=direction, protocol=protocol, at_s=at_s)
        assert _record(got) == _record(want)
        at_s += 0.02
    assert topo.counters()["clients"][1]["up"] == nets[(1, "up")].counters()["up"]


# -- bad input ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, named", [
    ({"access": "no-such-profile"}, "profile"), ({"server": "no-such-profile"}, "profile"),
    ({"clients": 0}, "clients"), ({"clients": -3}, "clients"), ({"clients": 1.5}, "clients"),
    ({"seed": "x"}, "seed"), ({"server": "bw=0"}, "bandwidth"), ({"server": "bw=50mbps,cc=newreno"}, "access spec"),
])
def test_bad_topologies_raise_one_line_netsim_errors(kwargs, named):
    with pytest.raises(netsim.NetsimError, match=named) as error:
        netsim.make_topology(**{"access": "lan-home", "server": "bw=50mbps", "clients": 2, **kwargs})
    assert "\n" not in str(error.value) and isinstance(error.value, ValueError)


@pytest.mark.parametrize("server", [None, "bw=50mbps,delay=5ms"])
def test_bad_sends_raise_one_line_netsim_errors(server):
    topo = netsim.make_topology(access="lan-home", server=server, clients=2, seed=0)
    topo.send(1_000, client=1, direction="up", at_s=1.0)
    cases = [({"client": 2}, "out of range"), ({"client": -1}, "out of range"), ({"client": True}, "client"),
             ({"client": 1, "direction": "up", "at_s": 0.5}, "must not decrease"),
             ({"direction": "sideways"}, "direction"), ({"protocol": "quic"}, "protocol"),
             ({"at_s": math.nan}, "time"), ({"deadline_s": 0.0}, "deadline")]
    for kwargs, named in cases:
        with pytest.raises(netsim.NetsimError, match=named) as error:
            topo.send(1_000, **kwargs)
        assert "\n" not in str(error.value)
    with pytest.raises(netsim.NetsimError, match="size"):
        topo.send(0, client=0)
    topo.send(1_000, client=0, direction="down", at_s=0.2)  # other pairs may still send earlier than 1.0
    topo.advance(2.0)
    with pytest.raises(netsim.NetsimError, match="before the last advance"):
        topo.send(1_000, client=0, direction="down", at_s=1.5)
    with pytest.raises(netsim.NetsimError, match="advance"):
        topo.advance(-1.0)


# -- physics: one client, two links in series ---------------------------------------------------------------------
def test_one_client_over_an_ideal_access_link_is_the_single_link_engine_bit_for_bit():
    # With an ideal access link the path is the server link alone; netsim.tcp and the joint engine then implement
    # the same rules on the same loss stream (server_seed), message for message.
    for link, transport in [("bw=50mbps,delay=10ms,queue=100p", "cc=cubic"),
                            ("bw=20mbps,delay=15ms,loss=2%,jitter=1ms", "cc=newreno"),
                            ("bw=100mbps,delay=5ms,loss=1%,queue=50p", "sack=off"),
                            ("bw=10mbps,delay=20ms,loss=3%", "delack=on,handshake=on")]:
        topo = netsim.make_topology(access="ideal," + transport, server=link, clients=1, seed=4)
        net = netsim.make_network(link + "," + transport, seed=netsim.server_seed(4, "down"))
        at_s = 0.0
        for size in (1_000, 300_000, 2_000_000, 40_000):
            want = net.send(size, at_s=at_s)
            got = topo.send(size, at_s=at_s)
            assert (got.arrival_s, got.delivered_bytes, got.lost_ranges) == \
                (want.arrival_s, want.delivered_bytes, want.lost_ranges)
            # The joint engine counts resends until the message settles; the single-link engine also counts
            # spurious ones after its last byte arrived.
            assert got.retransmissions <= want.retransmissions
            at_s = want.arrival_s + 0.5  # one message at a time: the single-link engine is exact there


def test_a_very_fast_access_link_changes_almost_nothing():
    server = "bw=50mbps,delay=10ms,loss=0.5%"
    fast = netsim.make_topology(access="bw=100gbps,delay=0ms", server=server, clients=1, seed=1)
    net = netsim.make_network(server, seed=netsim.server_seed(1, "down"))
    got, want = fast.send(4_000_000, at_s=0.0), net.send(4_000_000, at_s=0.0)
    assert got.arrival_s == pytest.approx(want.arrival_s, rel=0.01)


@pytest.mark.parametrize("access_mbps, server_mbps", [(20, 50), (50, 20)])
def test_a_long_transfer_takes_size_over_the_slower_link_plus_the_delays(access_mbps, server_mbps):
    # 20 MB through two links in series (5 ms + 10 ms one way): the slower link sets the pace. Bound: the bytes
    # on the wire at the bottleneck rate plus one one-way delay; slow start's first round trips (a few times
    # 30 ms) are the only overhead, so 3 % of the ~8.4 s is ample.
    size = 20_000_000
    topo = netsim.make_topology(access=f"bw={access_mbps}mbps,delay=5ms", server=f"bw={server_mbps}mbps,delay=10ms",
                                clients=1, seed=0)
    bound_s = size * WIRE_PER_PAYLOAD * 8 / (min(access_mbps, server_mbps) * 1e6) + 0.015
    for direction in ("down", "up"):
        d = topo.send(size, direction=direction, at_s=0.0)
        assert bound_s < d.arrival_s < bound_s * 1.03


# -- sharing one drop-tail queue ----------------------------------------------------------------------------------
SIZE = 5_000_000
NARROW = "bw=20mbps,delay=10ms,queue=100p"
FAST_ACCESS = "bw=1000mbps,delay=1ms,queue=1000p"


def _alone_and_shared(n, direction="down", cc="cubic"):
    access = f"{FAST_ACCESS},cc={cc}"
    alone = netsim.make_topology(access=access, server=NARROW, clients=1, seed=0).send(
        SIZE, direction=direction, at_s=0.0).arrival_s
    topo = netsim.make_topology(access=access, server=NARROW, clients=n, seed=0)
    deliveries = [topo.send(SIZE, client=i, direction=direction, at_s=0.0) for i in range(n)]
    return alone, [d.arrival_s for d in deliveries]  # read after all sends: earlier reads are tentative


def _jain(values):
    return sum(values) ** 2 / (len(values) * sum(v * v for v in values))


@pytest.mark.parametrize("direction", ["down", "up"])
@pytest.mark.parametrize("cc", ["cubic", "newreno"])
def test_two_equal_flows_each_get_about_half(direction, cc):
    # Alone, a flow takes T1 ~ S/B. Two flows keep the link busy (drop-tail, 100 packets of buffer): together
    # they finish by ~2 S/B, and the first one finishes at S / (x B) if it got a share x of the link meanwhile.
    # Allowing at most a 60/40 split over its lifetime: first >= 2 S/B * (0.5 / 0.6) = 0.83 * 2 S/B. Slow start,
    # one or two loss episodes and the 20 ms round trips cost well under 5 % of the 4.1 s.
    alone, shared = _alone_and_shared(2, direction, cc)
    both_s = 2 * SIZE * WIRE_PER_PAYLOAD * 8 / 20e6
    assert alone == pytest.approx(both_s / 2, rel=0.06)
    assert both_s * 0.83 <= min(shared) and max(shared) <= both_s * 1.05
    assert 1.66 <= min(shared) / alone and max(shared) / alone <= 2.1


@pytest.mark.parametrize("cc", ["cubic", "newreno"])
def test_eight_flows_share_the_link(cc):
    # Eight flows: together 8 S/B; each flow's average throughput within a factor 0.75 of the fair 1/8 (the first
    # to finish no earlier than 0.75 of the last), and Jain's index over their throughputs >= 0.98.
    alone, shared = _alone_and_shared(8, "down", cc)
    all_s = 8 * SIZE * WIRE_PER_PAYLOAD * 8 / 20e6
    assert all_s * 0.75 <= min(shared) and max(shared) <= all_s * 1.05
    assert _jain([SIZE / t for t in shared]) >= 0.98
    assert max(shared) / alone == pytest.approx(8, rel=0.06)


def test_a_narrow_server_link_slows_everyone_and_a_wide_one_does_not():
    def run(server, clients):
        topo = netsim.make_topology(access="lan-home", server=server, clients=clients, seed=0)
        deliveries = [topo.send(1_000_000, client=i, at_s=0.0) for i in range(clients)]
        return [d.arrival_s for d in deliveries]

    wide = "bw=10gbps,delay=1ms"
    alone = run(wide, 1)[0]
    # 4 x 800 Mbit/s fit in 10 Gbit/s: at most the other clients' first windows (3 x 10 packets, 1.2 us each)
    # queue ahead of a packet.
    for t in run(wide, 4):
        assert alone <= t <= alone + 30 * 1500 * 8 / 10e9 + 1e-9
    narrow = run("bw=20mbps,delay=1ms,queue=200p", 4)
    assert min(narrow) > 10 * alone
    assert max(narrow) >= 4 * 1_000_000 * WIRE_PER_PAYLOAD * 8 / 20e6  # 4 MB through 20 Mbit/s


def test_udp_and_tcp_share_the_link():
    # A UDP sender paced at 25 Mbit/s and a TCP bulk flow on a 50 Mbit/s bottleneck: UDP does not back off, TCP
    # gets what is left (~25 Mbit/s less its headers) and makes the shared queue overflow now and then, which
    # costs UDP a few datagrams.
    access = f"{FAST_ACCESS},pacing=25mbps"
    server = "bw=50mbps,delay=10ms,queue=100p"
    topo = netsim.make_topology(access=access, server=server, clients=2, seed=0)
    udp = topo.send(6_250_000, client=0, protocol="udp", at_s=0.0)
    tcp = topo.send(5_000_000, client=1, protocol="tcp", at_s=0.0)
    alone = netsim.make_topology(access=access, server=server, clients=2, seed=0).send(5_000_000, client=1)
    assert alone.arrival_s < 1.0  # 5 MB at 50 Mbit/s: 0.82 s and slow start
    leftover_s = 5_000_000 * WIRE_PER_PAYLOAD * 8 / (50e6 - 25e6 * 1500 / 1472)
    assert tcp.arrival_s == pytest.approx(leftover_s, rel=0.1)
    assert 0 < len(udp.lost_ranges) and 0.9 * 6_250_000 < udp.delivered_bytes < 6_250_000
    assert udp.delivered_bytes + sum(b - a for a, b in udp.lost_ranges) == 6_250_000


def test_udp_nack_fec_and_deadlines_work_in_a_topology():
    topo = netsim.make_topology(access="bw=100mbps,delay=2ms,loss=5%,nack=3", server="bw=50mbps,delay=5ms",
                                clients=2, seed=3)
    repaired = topo.send(500_000, client=0, protocol="udp", at_s=0.0)
    assert repaired.complete and repaired.retransmissions > 0
    late = topo.send(1_000_000, client=1, protocol="udp", at_s=0.0, deadline_s=0.05)
    assert not late.complete and late.settled_s <= 0.05 + 1e-12
    assert late.delivered_bytes + sum(b - a for a, b in late.lost_ranges) == 1_000_000
    fec = netsim.make_topology(access="bw=100mbps,delay=2ms,loss=2%,fec_k=8,fec_r=2", server="bw=50mbps",
                               clients=1, seed=0).send(300_000, protocol="udp", at_s=0.0)
    assert fec.complete and fec.retransmissions == 0


# -- guarantees ---------------------------------------------------------------------------------------------------
SPEC_ACCESS = "bw=40mbps,delay=3ms,jitter=1ms,loss=0.5%,queue=200p"
SPEC_SERVER = "bw=30mbps,delay=8ms,queue=150p,loss=0.2%"


def _random_sends(seed, clients=3, count=40, horizon_s=2.0):
    rng = random.Random(seed)
    sends = []
    for _ in range(count):
        sends.append({"size_bytes": rng.choice([2_000, 30_000, 150_000, 600_000]),
                      "client": rng.randrange(clients), "direction": rng.choice(["down", "up"]),
                      "protocol": rng.choice(["tcp", "tcp", "udp"]), "at_s": round(rng.uniform(0, horizon_s), 3),
                      "deadline_s": rng.choice([None, None, None, 0.3])})
    # Equal times on purpose: clients sending at the same instant must not depend on who was submitted first.
    sends += [dict(sends[0], client=c, protocol="tcp", deadline_s=None) for c in range(clients)]
    return sends


def _submit(order, clients=3, reads=False, advances=()):
    """Submit (key, send) pairs in this order; ``advances``: promise each frontier as soon as no remaining send
    comes earlier; ``reads``: read every delivery right after submitting it."""
    topo = netsim.make_topology(access=SPEC_ACCESS, server=SPEC_SERVER, clients=clients, seed=11)
    deliveries = {}
    pending = sorted(advances)
    for j, (key, send) in enumerate(order):
        earliest_left = min(s["at_s"] for _, s in order[j:])
        while pending and pending[0] <= earliest_left:
            topo.advance(pending.pop(0))
        deliveries[key] = topo.send(**send)
        if reads:
            deliveries[key].arrival_s  # a tentative read, invalidated by later submissions
    return topo, {key: _record(d) for key, d in deliveries.items()}


def _per_pair_time_order(sends):
    return sorted(enumerate(sends), key=lambda kv: (kv[1]["at_s"], kv[0]))


def test_the_same_sends_give_bit_identical_results():
    sends = _per_pair_time_order(_random_sends(1))
    assert _submit(sends)[1] == _submit(sends)[1]


def test_results_do_not_depend_on_the_submission_order_across_pairs():
    sends = _random_sends(2)
    in_time = _per_pair_time_order(sends)
    # Another order: pair by pair (each pair's own sends still in time order), reading results as we go.
    by_pair = sorted(in_time, key=lambda kv: (kv[1]["client"], kv[1]["direction"]))
    _, a = _submit(in_time)
    topo_b, b = _submit(by_pair, reads=True)
    # And the time order again, promising a frontier now and then (checkpoints, no re-simulation before them).
    topo_c, c = _submit(in_time, reads=True, advances=(0.5, 1.0, 1.5))
    assert a == b == c
    assert topo_b.counters() == topo_c.counters()


@pytest.mark.parametrize("seed", [3, 4])
def test_a_later_send_never_changes_a_message_that_settled_before_it(seed):
    sends = _per_pair_time_order(_random_sends(seed, horizon_s=1.0))
    _, before = _submit(sends)
    last = {}
    for _, s in sends:
        last[(s["client"], s["direction"])] = s["at_s"]
    changed_any = False
    checked = 0
    for extra_t in (0.2, 0.4, 0.6, 0.8, 1.0):
        for direction in ("down", "up"):
            # A pair that has not sent after extra_t (its sends must stay in time order).
            free = [c for c in range(3) if last.get((c, direction), 0.0) <= extra_t]
            if not free:
                continue
            extra = {"size_bytes": 2_000_000, "client": free[0], "direction": direction, "protocol": "tcp",
                     "at_s": extra_t}
            _, after = _submit(sends + [(len(sends), extra)])
            for key, record in before.items():
                if record[1] < extra_t:  # settled before the extra send: untouched
                    assert after[key] == record
                    checked += 1
                elif after[key] != record:
                    changed_any = True
    assert checked and changed_any  # the extra sends matter, just never to what was over


def test_a_tentative_delivery_is_updated_in_place_by_an_earlier_send_of_another_client():
    topo = netsim.make_topology(access=FAST_ACCESS, server=NARROW, clients=2, seed=0)
    late = topo.send(2_000_000, client=1, at_s=0.5)
    alone_s = late.arrival_s
    early = topo.send(2_000_000, client=0, at_s=0.0)  # submitted later, sent earlier: shares the link with it
    assert late.arrival_s > alone_s + 0.3 and early.arrival_s < late.arrival_s
    topo.advance(0.5)
    assert late.arrival_s == late.arrival_s  # stable once read


def test_advance_moves_the_checkpoint_without_changing_results():
    sends = _per_pair_time_order(_random_sends(5))
    _, plain = _submit(sends)
    _, checkpointed = _submit(sends, reads=True, advances=[0.1 * k for k in range(1, 20)])
    assert plain == checkpointed


def test_vectorised_and_scalar_tcp_paths_agree_bit_for_bit(monkeypatch):
    # The single-link engine's vectorised ACK batches must give exactly the scalar path's results: a replayed
    # busy period can switch between the two, and an earlier message would otherwise move.
    def run():
        out = []
        for spec in ("bw=50mbps,delay=10ms", "wan-50m", "bw=100mbps,delay=20ms,loss=1%,queue=100p",
                     "bw=1000mbps,delay=50ms,loss=5%,sack=off"):
            net = netsim.make_network(spec, seed=2)
            at_s = 0.0
            for size in (1_000_000, 300_000, 2_000_000):
                d = net.send(size, at_s=at_s)
                out.append(_record(d))
                at_s = d.arrival_s + 0.5
        return out

    vectorised = run()
    monkeypatch.setattr(link_module.Link, "vector_ok", property(lambda self: False))
    assert run() == vectorised


def test_a_later_send_on_the_same_connection_does_not_move_an_arrived_message():
    for spec in ("bw=50mbps,delay=10ms", "wan-50m", "bw=100mbps,delay=20ms,loss=1%"):
        for seed in range(3):
            net = netsim.make_network(spec, seed=seed)
            first = net.send(1_000_000, at_s=0.0)
            before = _record(first)
            net.send(1_000_000, at_s=first.arrival_s + 1e-6)  # joins the busy period (the last ACK is not back)
            assert _record(first) == before


# -- cost: copy-on-write checkpoints ------------------------------------------------------------------------------
def _count_copies(monkeypatch):
    """Count engine copies and the flow and link copies that copy-on-write makes."""
    from netsim import engine as engine_module

    counts = {"engines": 0, "flows": 0, "links": 0}

    def counting(cls, name, key):
        original = getattr(cls, name)

        def wrapper(self, *args, **kwargs):
            counts[key] += 1
            return original(self, *args, **kwargs)
        monkeypatch.setattr(cls, name, wrapper)

    counting(engine_module.Engine, "clone", "engines")
    counting(engine_module.TcpFlow, "clone", "flows")
    counting(engine_module.UdpFlow, "clone", "flows")
    counting(link_module.Link, "copy", "links")
    return counts


def _busy_few_clients(clients):
    """Clients 0-3 of ``clients`` exchange messages frame after frame from 1 s on, reading results between sends
    (each read after a send that lands in simulated time copies the checkpoint); the others received one message
    each at 0 s and are idle since. The server link is lossless and drained by 1 s, so they leave no trace."""
    topo = netsim.make_topology(access=SPEC_ACCESS, server="bw=30mbps,delay=8ms,queue=150p", clients=clients,
                                seed=5)
    records = []
    for i in range(4, clients):
        topo.send(20_000, client=i, direction=("down", "up")[i % 2], protocol=("tcp", "udp")[i % 3 == 0], at_s=0.0)
    topo.advance(1.0)  # the checkpoint: every flow of clients 4.. idle
    for k in range(12):
        t = 1.0 + 0.02 * k
        down = topo.send(60_000, client=k % 4, direction="down", protocol="tcp", at_s=t)
        up = topo.send(8_000, client=(k + 1) % 4, direction="up", protocol="udp", at_s=t + 0.001)
        records.append(_record(down))
        records.append(_record(up))
        late = topo.send(30_000, client=(k + 2) % 4, direction="down", protocol="tcp", at_s=t)  # in simulated time
        records.append(_record(late))
        topo.advance(t)
    return topo, records


def test_a_checkpoint_copy_does_not_copy_idle_flows_or_links(monkeypatch):
    counts = _count_copies(monkeypatch)
    _, few = _busy_few_clients(4)
    small = dict(counts)
    for key in counts:
        counts[key] = 0
    topo, many = _busy_few_clients(64)
    # The 60 idle clients change nothing, cost nothing: the same results, the same copies.
    assert many == few
    assert counts == small
    assert counts["engines"] >= 12  # the reads did copy the checkpoint, many times
    # After a copy both engines share everything, and either copies what it changes: at most the busy clients'
    # 16 flows and 10 links (with the server link's two) each. A full copy would take 256 flows and 130 links.
    assert counts["flows"] <= 2 * 16 * counts["engines"] and counts["links"] <= 2 * 10 * counts["engines"]
    # And in place: the tentative engine still shares every idle client's flows and links with the checkpoint.
    tentative, committed = topo._current(), topo._committed
    assert tentative is not committed
    idle = range(8, 64)
    assert all(tentative.flows[f] is committed.flows[f] for i in idle for f in range(4 * i, 4 * i + 4))
    assert all(tentative.links[k] is committed.links[k] for i in idle for k in (2 + 2 * i, 3 + 2 * i))


def _message_record(message):
    return (message.arrival_s, message.settled_s, message.delivered_bytes, tuple(message.lost_ranges),
            message.retransmissions, message.complete)


def _engine_record(engine, messages):
    links = [(link.packets_offered, link.packets_sent, link.packets_lost, link.packets_dropped_queue,
              link.bytes_sent, link.busy_until_s, link.last_arrival_s) for link in engine.links]
    flows = [(flow.retransmissions, getattr(flow, "timeouts", None), getattr(flow, "segments_sent", None),
              getattr(flow, "datagrams_sent", None), flow.token) for flow in engine.flows]
    return [_message_record(m) for m in messages], links, flows


def test_an_engine_and_its_copies_run_on_independently_and_bit_identically():
    # Copies share flows and links until one of them changes one; whichever runs first, and however they
    # interleave, each gives what an engine that never stopped gives (lossy links with jitter: random streams too).
    sends = [s for _, s in _per_pair_time_order(_random_sends(6, clients=3, count=30, horizon_s=1.0))]

    def submitted():
        topo = netsim.make_topology(access=SPEC_ACCESS, server=SPEC_SERVER, clients=3, seed=2)
        messages = [topo.send(**s)._message for s in sends]
        return topo._committed, messages

    plain, messages = submitted()
    plain.run()
    want = _engine_record(plain, messages)

    engine, messages = submitted()
    engine.run(until_s=0.3)
    first = engine.clone()
    engine.run(until_s=0.6)        # the original moves on while its first copy waits
    second = engine.clone()
    third = second.clone()          # a copy of a copy
    first.run(until_s=0.9)
    second.run()
    got_second = _engine_record(second, messages)
    engine.run(until_s=0.9)
    first.run()
    got_first = _engine_record(first, messages)
    engine.run()
    got_engine = _engine_record(engine, messages)
    third.run()
    got_third = _engine_record(third, messages)
    assert got_second == got_first == got_engine == got_third == want
    assert sum(m.complete for m in messages) > 10
