"""UDP messages: datagrams of at most MTU - 28 payload bytes, paced (by default at the link's rate) or in one
burst, nothing retransmitted unless asked. The receiver learns exactly which byte ranges are missing, so a method can decide what to do with them.

Options (``UdpConfig``):
- NACK rounds: when the receiver expects the end of a pass (the arrival of its last datagram, or one one-way
  delay after the sender's last send if that datagram was lost) it reports the missing datagrams; the report
  reaches the sender one reverse delay later and the sender resends them; up to ``nack_rounds`` times.
- Block FEC: every ``fec_k`` data datagrams are followed by ``fec_r`` parity datagrams (full payload size, so the
  bandwidth cost is r/k). A block with at most r lost datagrams is recovered completely once k of its k + r
  datagrams are in (an MDS code such as Reed-Solomon); the last block may be shorter than k.
- Deadline: data arriving later than ``at_s + deadline_s`` counts as lost.

Example::

    env = Environment(seed=0)
    down = Link(env, LinkConfig(bandwidth_mbps=40, delay_ms=3, loss=0.05), "down")
    udp = UdpSender(env, down, reverse_delay_s=0.003, config=UdpConfig(fec_k=8, fec_r=2))
    message = udp.put(Message(size_bytes=100_000, at_s=0.0))
    print(message.lost_ranges, message.delivered_bytes)
"""

from __future__ import annotations

import math

from netsim.config import UDP_HEADER_BYTES, UdpConfig
from netsim.env import Environment
from netsim.link import Link
from netsim.tcp import Message


class UdpSender:
    """Counters: ``datagrams_sent``, ``parity_sent``, ``retransmissions``, ``datagrams_recovered``."""

    def __init__(self, env: Environment, link: Link, reverse_delay_s: float, config: UdpConfig,
                 max_sim_time_s: float = 600.0):
        self.env = env
        self.link = link
        self.config = config
        self.payload_bytes = link.config.mtu_bytes - UDP_HEADER_BYTES
        self.reverse_delay_s = reverse_delay_s
        self.max_sim_time_s = max_sim_time_s
        self.out: list[Message] = []
        self.datagrams_sent = 0
        self.parity_sent = 0
        self.retransmissions = 0
        self.datagrams_recovered = 0

    def _send_pass(self, sizes: list[int], start_s: float) -> tuple[list[float], float]:
        """Send datagrams (payload sizes) from ``start_s``; return arrival times (inf = lost) and the last send."""
        if self.config.burst:
            gap_per_byte_s = 0.0
        elif self.config.pacing_mbps:
            gap_per_byte_s = 8.0 / (self.config.pacing_mbps * 1e6)
        else:
            gap_per_byte_s = 1.0 / self.link.rate_bytes_per_s  # at the link's rate: no queue builds up
        transmit = self.link.transmit
        arrivals = []
        t = start_s
        for size in sizes:
            wire = size + UDP_HEADER_BYTES
            arrival = transmit(t, wire, self)
            arrivals.append(math.inf if arrival is None else arrival)
            self.datagrams_sent += 1
            last_send_s = t
            t += wire * gap_per_byte_s
        return arrivals, (last_send_s if sizes else start_s)

    def put(self, message: Message) -> Message:
        config = self.config
        size = message.size_bytes
        payload = self.payload_bytes
        count = -(-size // payload)
        sizes = [payload] * (count - 1) + [size - payload * (count - 1)]
        k, r = config.fec_k, config.fec_r
        # Datagram layout of the first pass: data, with r parity datagrams after every k data datagrams.
        layout: list[tuple[int, int]] = []  # (data index or -1 for parity, block)
        wire_sizes: list[int] = []
        for i, s in enumerate(sizes):
            layout.append((i, i // k if r else 0))
            wire_sizes.append(s)
            if r and ((i + 1) % k == 0 or i == count - 1):
                for _ in range(r):
                    layout.append((-1, i // k))
                    wire_sizes.append(payload)
                    self.parity_sent += 1
        # The link is FIFO: a message offered while the link is still busy waits behind the earlier packets.
        start_s = message.at_s
        arrivals, last_send_s = self._send_pass(wire_sizes, start_s)
        data_arrival = [math.inf] * count
        block_arrivals: dict[int, list[float]] = {}
        block_data_lost: dict[int, list[int]] = {}
        for (index, block), arrival in zip(layout, arrivals):
            if r:
                block_arrivals.setdefault(block, []).append(arrival)
            if index >= 0:
                data_arrival[index] = arrival
                if arrival == math.inf and r:
                    block_data_lost.setdefault(block, []).append(index)
        if r:
            for block, lost in block_data_lost.items():
                received = sorted(a for a in block_arrivals[block] if a < math.inf)
                block_size = min(k, count - block * k)
                if len(received) >= block_size:
                    # Decodable once any block_size of the block's datagrams are in.
                    recovered_s = received[block_size - 1]
                    for index in lost:
                        data_arrival[index] = recovered_s
                        self.datagrams_recovered += 1
        # NACK rounds: the receiver reports holes at the expected end of the pass.
        for _ in range(config.nack_rounds):
            missing = [i for i, a in enumerate(data_arrival) if a == math.inf]
            if not missing:
                break
            received_times = [a for a in arrivals if a < math.inf]
            expected_end_s = max(max(received_times, default=0.0),
                                 last_send_s + self.link.delay_s + self.link.serialisation_s(payload + UDP_HEADER_BYTES))
            resend_s = expected_end_s + self.reverse_delay_s
            if resend_s - message.at_s > self.max_sim_time_s:
                break
            arrivals, last_send_s = self._send_pass([sizes[i] for i in missing], resend_s)
            self.retransmissions += len(missing)
            message.retransmissions += len(missing)
            for i, arrival in zip(missing, arrivals):
                data_arrival[i] = arrival
        deadline_abs_s = message.at_s + message.deadline_s if message.deadline_s is not None else math.inf
        lost_ranges: list[tuple[int, int]] = []
        delivered = 0
        last_arrival = message.at_s
        for i, arrival in enumerate(data_arrival):
            begin = i * payload
            end = begin + sizes[i]
            if arrival <= deadline_abs_s and arrival < math.inf:
                delivered += sizes[i]
                if arrival > last_arrival:
                    last_arrival = arrival
            elif lost_ranges and lost_ranges[-1][1] == begin:
                lost_ranges[-1] = (lost_ranges[-1][0], end)
            else:
                lost_ranges.append((begin, end))
        message.delivered_bytes = delivered
        message.lost_ranges = lost_ranges
        message.complete = not lost_ranges
        message.arrival_s = last_arrival if message.complete else math.inf
        # When the receiver holds everything it will get: the last useful arrival, or the deadline.
        message.settled_s = last_arrival if message.complete else min(
            deadline_abs_s, max([a for a in data_arrival if a < math.inf], default=message.at_s))
        self.out.append(message)
        return message


if __name__ == "__main__":
    from netsim.config import LinkConfig

    env = Environment(seed=0)
    down = Link(env, LinkConfig(bandwidth_mbps=40, delay_ms=3, loss=0.05), "down")
    udp = UdpSender(env, down, reverse_delay_s=0.003, config=UdpConfig(fec_k=8, fec_r=2))
    message = udp.put(Message(size_bytes=100_000, at_s=0.0))
    print(f"delivered {message.delivered_bytes} of 100000 bytes, lost ranges {message.lost_ranges}, "
          f"{udp.datagrams_recovered} datagrams recovered by FEC")
