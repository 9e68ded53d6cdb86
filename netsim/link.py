"""One direction of a path: drop-tail queue -> serialisation at the link rate (or a Mahimahi trace) -> random
loss -> propagation delay + jitter.

The link is a component in the simpy style (``env`` first, ``put()`` in, ``.out`` out, public counters) but it
does not schedule events: a FIFO link is a recurrence, so ``transmit()`` computes a packet's departure and arrival
in O(1) when the packet is offered. Offers must come in non-decreasing time (the transports guarantee it), which is
what keeps an 8 MB transfer to a few milliseconds of CPU (docs/netsim.md, "Granularity").

Example::

    from netsim.env import Environment
    from netsim.config import LinkConfig
    env = Environment(seed=0)
    link = Link(env, LinkConfig(bandwidth_mbps=10, delay_ms=5), name="down")
    link.put(Packet(size_bytes=1500, sent_s=0.0))
    print(link.out[0].arrival_s)   # 0.0062 = 1.2 ms serialisation + 5 ms propagation
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from netsim.config import LinkConfig
from netsim.env import Environment
from netsim.traces import MAHIMAHI_PACKET_BYTES, TraceCapacity, load_mahimahi

_BLOCK = 4096  # random numbers drawn per refill; blocks keep draws cheap and the stream identical per seed


@dataclass
class Packet:
    size_bytes: int
    sent_s: float
    arrival_s: float = math.inf
    dropped: bool = False
    tag: object = None


class RandomStream:
    """Uniform(0,1) numbers from a seeded generator, served one by one from numpy blocks.

    Copies share the generator until one of them needs a new block (copy on write): the topology engine copies
    a link whenever a checkpoint's copy first offers it a packet, and most links (no loss, no jitter) never draw
    at all.
    """

    def __init__(self, rng: np.random.Generator):
        self._rng = rng
        self._owned = True  # False: the generator may be shared with a copy; take a private one before drawing
        self._block: list[float] = []
        self._index = 0

    def _generator(self) -> np.random.Generator:
        if not self._owned:
            rng = self._rng
            bit_generator = type(rng.bit_generator)(0)
            bit_generator.state = rng.bit_generator.state
            self._rng = np.random.Generator(bit_generator)
            self._owned = True
        return self._rng

    def next(self) -> float:
        if self._index >= len(self._block):
            self._block = self._generator().random(_BLOCK).tolist()
            self._index = 0
        value = self._block[self._index]
        self._index += 1
        return value

    def peek(self, count: int) -> np.ndarray:
        """The next ``count`` numbers, without consuming them (same sequence as ``next()``)."""
        remaining = len(self._block) - self._index
        if remaining < count:
            self._block = self._block[self._index:] + self._generator().random(
                max(_BLOCK, count - remaining)).tolist()
            self._index = 0
        return np.array(self._block[self._index:self._index + count])

    def skip(self, count: int) -> None:
        self._index += count

    def state(self):
        return (self._rng.bit_generator.state, list(self._block), self._index)

    def restore(self, state) -> None:
        self._generator().bit_generator.state = state[0]
        self._block = list(state[1])
        self._index = state[2]

    def copy(self) -> "RandomStream":
        """An independent stream that continues with the same numbers. Blocks are never modified in place, so
        the current one is shared; so is the generator, until either stream draws from it."""
        other = RandomStream.__new__(RandomStream)
        other._rng = self._rng
        other._owned = False
        self._owned = False
        other._block = self._block
        other._index = self._index
        return other


class Link:
    """A unidirectional bottleneck link (see :class:`netsim.config.LinkConfig` for the parameters).

    Counters: ``packets_offered``, ``packets_sent``, ``packets_dropped_queue``, ``packets_lost``, ``bytes_sent``.
    """

    def __init__(self, env: Environment, config: LinkConfig, name: str = "down"):
        self.env = env
        self.config = config
        self.name = name
        self.out: list[Packet] = []
        self.rate_bytes_per_s = config.bandwidth_mbps * 1e6 / 8
        self.delay_s = config.delay_ms * 1e-3
        self.jitter_s = config.jitter_ms * 1e-3
        self.queue_bytes = config.queue_bytes
        self.overhead_bytes = config.link_overhead_bytes  # link-layer framing per packet (PPP: 2 bytes)
        self._queue_limit_bytes = config.queue_bytes + config.mtu_bytes
        self.trace = TraceCapacity(load_mahimahi(config.trace_path)) if config.trace_path else None
        if self.trace is not None:
            self.rate_bytes_per_s = self.trace.per_period * MAHIMAHI_PACKET_BYTES / self.trace.period_s
        self._loss_stream = RandomStream(env.rng(f"{name}/loss"))
        self._jitter_stream = RandomStream(env.rng(f"{name}/jitter"))
        self._jitter_kind = config.jitter_distribution if config.jitter_ms > 0 else "none"
        if self._jitter_kind == "none" and config.jitter_ms > 0:
            self._jitter_kind = "exponential"
        self._gilbert = config.ge_p > 0
        self._loss = config.loss
        self._reorder = config.reorder
        self.busy_until_s = 0.0      # when the transmitter finishes the last accepted packet
        self.last_arrival_s = 0.0    # keeps arrivals in order (no reordering unless asked)
        self.ge_bad = False          # Gilbert-Elliott state
        self._trace_bytes_served = 0  # bytes through the trace's opportunities so far
        self.last_user: object = None  # which flow offered the last packet (transports use it to share the link)
        self._owner: object = None     # the topology engine that may change this link in place (copy-on-write)
        # Packets to lose on purpose, by offer number (0 = the first packet offered): scripted experiments and
        # tests that need a loss at an exact place. They add to the random loss.
        self.scripted_losses: set[int] = set()
        self.packets_offered = 0
        self.packets_sent = 0
        self.packets_dropped_queue = 0
        self.packets_lost = 0
        self.bytes_sent = 0

    # -- the hot path ------------------------------------------------------------------------------------------
    def transmit(self, t_s: float, wire_bytes: int, user: object = None, keep_order: bool = False) -> float | None:
        """Offer a packet of ``wire_bytes`` (headers included) at time ``t_s``; return its arrival time at the far
        end, or None when the queue or the channel dropped it. ``keep_order``: never let this packet overtake
        (TCP's model assumes in-order delivery even on a link that reorders UDP datagrams)."""
        offer_number = self.packets_offered
        self.packets_offered += 1
        wire_bytes += self.overhead_bytes
        self.last_user = user
        busy = self.busy_until_s
        if self.trace is None:
            if busy > t_s:
                # Drop-tail (RFC 7567's tail drop): the bytes not yet sent, less the packet on the wire (at most
                # one MTU), plus this one must fit in the buffer.
                if (busy - t_s) * self.rate_bytes_per_s + wire_bytes > self._queue_limit_bytes:
                    self.packets_dropped_queue += 1
                    return None
                depart = busy + wire_bytes / self.rate_bytes_per_s
            else:
                depart = t_s + wire_bytes / self.rate_bytes_per_s
        else:
            depart = self._trace_depart(t_s, wire_bytes)
            if depart is None:
                self.packets_dropped_queue += 1
                return None
        self.busy_until_s = depart
        self.packets_sent += 1
        self.bytes_sent += wire_bytes
        # Loss on the wire: the packet used the link, then vanished (as ns-3's receive-side error model does).
        if self._gilbert:
            u = self._loss_stream.next()
            cfg = self.config
            if self.ge_bad:
                if u < cfg.ge_r:
                    self.ge_bad = False
            elif u < cfg.ge_p:
                self.ge_bad = True
            lost = self._loss_stream.next() < (cfg.ge_loss_bad if self.ge_bad else cfg.ge_loss_good)
        else:
            lost = self._loss > 0 and self._loss_stream.next() < self._loss
        if lost or (self.scripted_losses and offer_number in self.scripted_losses):
            self.packets_lost += 1
            return None
        arrive = depart + self.delay_s
        if self._jitter_kind != "none":
            arrive += self._jitter()
        if keep_order or not self._reorder:
            if arrive < self.last_arrival_s:
                arrive = self.last_arrival_s
            self.last_arrival_s = arrive
        return arrive

    def _jitter(self) -> float:
        u = self._jitter_stream.next()
        kind = self._jitter_kind
        if kind == "exponential":
            return -self.jitter_s * math.log(1.0 - u)
        if kind == "uniform":
            return self.jitter_s * u * 2.0  # uniform on [0, 2 * jitter]: mean = jitter
        # normal, truncated at zero (a packet is never early): Box-Muller with a second draw
        v = self._jitter_stream.next()
        z = math.sqrt(-2.0 * math.log(1.0 - u)) * math.cos(2.0 * math.pi * v)
        return max(0.0, self.jitter_s * z)

    def _trace_depart(self, t_s: float, wire_bytes: int) -> float | None:
        """Mahimahi semantics: bytes leave at opportunity instants, 1500 per opportunity; unused ones are lost."""
        trace = self.trace
        first_free = trace.first_index_at_or_after(t_s) * MAHIMAHI_PACKET_BYTES
        served = self._trace_bytes_served
        backlog = served - first_free
        if backlog > 0 and backlog + wire_bytes > self._queue_limit_bytes:
            return None
        end_bytes = max(served, first_free) + wire_bytes
        self._trace_bytes_served = end_bytes
        return trace.time_s(-(-end_bytes // MAHIMAHI_PACKET_BYTES) - 1)

    # -- the vectorised path (a run of packets known to be accepted and delivered) -------------------------------
    @property
    def vector_ok(self) -> bool:
        """Whether :meth:`transmit_many` applies (constant rate, Bernoulli loss)."""
        return self.trace is None and not self._gilbert

    def transmit_many(self, send_s: np.ndarray, wire_bytes: np.ndarray, user: object = None):
        """Vectorised :meth:`transmit` for packets in non-decreasing send order.

        Returns (arrival times, index of the first packet that the queue or the channel would drop, or None).
        Nothing is committed when a packet would be dropped: the caller shortens the run and calls again, or
        falls back to :meth:`transmit` for the problem packet.
        """
        count = len(send_s)
        rate = self.rate_bytes_per_s
        if self.overhead_bytes:
            wire_bytes = wire_bytes + self.overhead_bytes
        tx_s = (wire_bytes / rate).tolist()  # IEEE division: the same numbers transmit() computes
        sends = send_s.tolist()
        wires = wire_bytes.tolist()
        # The FIFO recurrence d_i = max(s_i, d_{i-1}) + tx_i, with the drop-tail test of transmit(), in the same
        # floating-point operations as transmit() so that both paths give bit-identical times (an unrolled numpy
        # form, cumulative sums and maxima, differs in the last bits, and a replayed busy period that switches
        # between the paths would then move an earlier message).
        limit = self._queue_limit_bytes
        busy = self.busy_until_s
        depart = []
        first_problem = count
        for i in range(count):
            t = sends[i]
            if busy > t:
                if (busy - t) * rate + wires[i] > limit:
                    first_problem = i
                    break
                busy = busy + tx_s[i]
            else:
                busy = t + tx_s[i]
            depart.append(busy)
        if self._loss > 0:
            lost = self._loss_stream.peek(count) < self._loss
            if lost.any():
                first_problem = min(first_problem, int(np.argmax(lost)))
        if self.scripted_losses:
            for number in self.scripted_losses:
                if self.packets_offered <= number < self.packets_offered + count:
                    first_problem = min(first_problem, number - self.packets_offered)
        if first_problem < count:
            return None, first_problem
        delay = self.delay_s
        kind = self._jitter_kind
        if kind == "none":
            arrive = [d + delay for d in depart]
        else:
            jitter_s = self.jitter_s
            if kind == "normal":
                pairs = self._jitter_stream.peek(2 * count).tolist()
                self._jitter_stream.skip(2 * count)
                # transmit()'s Box-Muller, number for number.
                extra = [max(0.0, jitter_s * (math.sqrt(-2.0 * math.log(1.0 - pairs[2 * i]))
                                              * math.cos(2.0 * math.pi * pairs[2 * i + 1])))
                         for i in range(count)]
            else:
                draws = self._jitter_stream.peek(count).tolist()
                self._jitter_stream.skip(count)
                if kind == "exponential":
                    extra = [-jitter_s * math.log(1.0 - u) for u in draws]
                else:
                    extra = [jitter_s * u * 2.0 for u in draws]
            arrive = [d + delay + e for d, e in zip(depart, extra)]
        arrive_s = np.array(arrive)
        depart_s = depart
        if True:  # the vectorised path serves TCP, which this model keeps in order (docs/netsim.md)
            arrive_s = np.maximum.accumulate(np.maximum(arrive_s, self.last_arrival_s))
            self.last_arrival_s = float(arrive_s[-1])
        if self._loss > 0:
            self._loss_stream.skip(count)
        self.busy_until_s = depart_s[-1]
        self.packets_offered += count
        self.packets_sent += count
        self.bytes_sent += int(wire_bytes.sum())
        self.last_user = user
        return arrive_s, None

    # -- simpy-style interface -----------------------------------------------------------------------------------
    def put(self, packet: Packet) -> Packet:
        arrival = self.transmit(packet.sent_s, packet.size_bytes, user=packet.tag)
        packet.arrival_s = math.inf if arrival is None else arrival
        packet.dropped = arrival is None
        if not packet.dropped:
            self.out.append(packet)
        return packet

    def serialisation_s(self, wire_bytes: int) -> float:
        return wire_bytes / self.rate_bytes_per_s

    # -- snapshots (a TCP busy period is re-simulated when a later message joins it) -----------------------------
    def snapshot(self):
        return (self.busy_until_s, self.last_arrival_s, self.ge_bad, self._trace_bytes_served, self.last_user,
                self.packets_offered, self.packets_sent, self.packets_dropped_queue, self.packets_lost,
                self.bytes_sent, self._loss_stream.state(), self._jitter_stream.state())

    def copy(self) -> "Link":
        """An independent link in the same state (queue, loss and jitter streams, counters): the topology engine
        checkpoints a simulation by copying its links."""
        other = object.__new__(Link)
        other.__dict__.update(self.__dict__)
        other.out = list(self.out)
        other.scripted_losses = set(self.scripted_losses)
        other._loss_stream = self._loss_stream.copy()
        other._jitter_stream = self._jitter_stream.copy()
        return other

    def restore(self, state) -> None:
        (self.busy_until_s, self.last_arrival_s, self.ge_bad, self._trace_bytes_served, self.last_user,
         self.packets_offered, self.packets_sent, self.packets_dropped_queue, self.packets_lost,
         self.bytes_sent, loss_state, jitter_state) = state
        self._loss_stream.restore(loss_state)
        self._jitter_stream.restore(jitter_state)


if __name__ == "__main__":
    env = Environment(seed=0)
    link = Link(env, LinkConfig(bandwidth_mbps=10, delay_ms=5, loss=0.1), name="down")
    for i in range(10):
        link.put(Packet(size_bytes=1500, sent_s=0.0, tag=i))
    print(f"sent {link.packets_sent}, lost {link.packets_lost}, arrivals:",
          [f"{p.arrival_s * 1e3:.2f} ms" for p in link.out])
