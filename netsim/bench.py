"""Speed benchmarks: CPU time to simulate an 8 MB TCP transfer (without loss and at 1 % loss), and a topology of
32 clients sharing a 100 Mbit/s server link.

Targets (issue 4): <= 20 ms of CPU without loss, <= 100 ms at 1 % loss. CPU time is ``time.process_time``; each
single-link figure is the median of several repeats with different seeds. Run: ``python -m netsim.bench``.

The topology case: 32 clients behind ``lan-home`` access links, a 100 Mbit/s, 5 ms, 1000-packet server link, and
every client receives a 100 kB TCP message every 100 ms for 5 s (1600 messages, ~256 Mbit/s offered: the server
link is 2.5 times overloaded and the backlog drains until ~13 s). "batch": all sends submitted, then every result
read; "per frame": each 100 ms, ``advance()`` to the frame, the 32 sends, then their results read (each read
re-simulates from the checkpoint to the end of the backlog, which is what an overloaded link costs). The event-loop
figures use 30 kB messages (no backlog) and a harness-like loop (:func:`event_loop_cpu_s`).
"""

from __future__ import annotations

import statistics
import time

import netsim

TRANSFER_BYTES = 8 * 1024 * 1024
# A 100 Mbit/s, 20 ms RTT path: enough segments in flight that the window logic is exercised.
BASE_SPEC = "bw=100mbps,rtt=20ms"
TOPOLOGY = {"access": "lan-home", "server": "bw=100mbps,delay=5ms,queue=1000p", "clients": 32}
FRAME_S = 0.1
FRAMES = 50
MESSAGE_BYTES = 100_000


def _cpu_ms(spec: str, seed: int) -> tuple[float, float]:
    net = netsim.make_network(spec, seed=seed)
    start = time.process_time()
    delivery = net.send(TRANSFER_BYTES, direction="down", protocol="tcp", at_s=0.0)
    return (time.process_time() - start) * 1e3, delivery.arrival_s


def topology_cpu_s(per_frame: bool = False, frames: int = FRAMES) -> tuple[float, float, int]:
    """(CPU seconds, last arrival, packets through the server link) for the 32-client case."""
    topo = netsim.make_topology(seed=0, **TOPOLOGY)
    start = time.process_time()
    deliveries = []
    for k in range(frames):
        at_s = k * FRAME_S
        if per_frame:
            topo.advance(at_s)
        frame = [topo.send(MESSAGE_BYTES, client=i, direction="down", protocol="tcp", at_s=at_s)
                 for i in range(TOPOLOGY["clients"])]
        if per_frame:
            [d.arrival_s for d in frame]
        deliveries += frame
    last = max(d.arrival_s for d in deliveries)
    cpu_s = time.process_time() - start
    return cpu_s, last, topo.counters()["server"]["down"]["packets_sent"]


def event_loop_cpu_s(message_bytes: int, read_after_each_send: bool, frames: int = FRAMES) -> tuple[float, float]:
    """(CPU seconds, last arrival) for a harness-like event loop: the clock visits every send time and every
    arrival in order and calls ``advance()`` whenever it moves; a client reads its message's arrival to know when
    to wake, and once more when woken. ``read_after_each_send``: each client reads right after its own send, before
    the other clients' sends at the same instant (each read then re-simulates from the checkpoint); otherwise all
    sends of an instant come first."""
    import heapq
    import itertools

    topo = netsim.make_topology(seed=0, **TOPOLOGY)
    order = itertools.count()
    heap = [(k * FRAME_S, 0, next(order), i, None) for k in range(frames) for i in range(TOPOLOGY["clients"])]
    heapq.heapify(heap)
    now_s = 0.0
    last = 0.0
    start = time.process_time()
    while heap:
        t_s, kind, _, client, delivery = heapq.heappop(heap)
        if t_s > now_s:
            now_s = t_s
            topo.advance(now_s)
        if kind == 0:
            delivery = topo.send(message_bytes, client=client, direction="down", protocol="tcp", at_s=now_s)
            wake_s = max(delivery.arrival_s, now_s) if read_after_each_send else now_s
            heapq.heappush(heap, (wake_s, 1, next(order), client, delivery))
        elif delivery.arrival_s > now_s:
            heapq.heappush(heap, (delivery.arrival_s, 1, next(order), client, delivery))
        else:
            last = max(last, delivery.arrival_s)
    return time.process_time() - start, last


def run(repeats: int = 7, topology: bool = True) -> dict:
    """{"tcp_8mb_lossless_cpu_ms": median, "tcp_8mb_loss1pct_cpu_ms": median, ...}."""
    results = {}
    for label, spec in (("lossless", BASE_SPEC), ("loss1pct", BASE_SPEC + ",loss=1%")):
        samples = [_cpu_ms(spec, seed) for seed in range(repeats)]
        results[f"tcp_8mb_{label}_cpu_ms"] = statistics.median(s[0] for s in samples)
        results[f"tcp_8mb_{label}_sim_s"] = statistics.median(s[1] for s in samples)
    results["targets_cpu_ms"] = {"lossless": 20.0, "loss1pct": 100.0}
    results["repeats"] = repeats
    if topology:
        for label, per_frame in (("batch", False), ("per_frame", True)):
            cpu_s, last_s, packets = topology_cpu_s(per_frame)
            results[f"topology_32_clients_{label}_cpu_s"] = cpu_s
        results["topology_32_clients_last_arrival_s"] = last_s
        results["topology_32_clients_server_packets"] = packets
        # The same 32 clients with 30 kB messages (77 Mbit/s offered: no backlog) in an event loop.
        results["topology_32_clients_30kb_event_loop_cpu_s"] = event_loop_cpu_s(30_000, False)[0]
        results["topology_32_clients_30kb_event_loop_read_after_each_send_cpu_s"] = event_loop_cpu_s(30_000, True)[0]
    return results


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
