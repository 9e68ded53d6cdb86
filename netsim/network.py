"""The harness-facing network: two links (down = server -> client, up = client -> server), one persistent TCP
connection per sending direction and a UDP sender per direction.

Example::

    net = make_network("wan-50m", seed=0)
    d = net.send(300_000, direction="down", protocol="tcp", at_s=0.0)
    print(d.arrival_s, d.retransmissions)
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Callable

from netsim.errors import NetsimError
from netsim.config import NetworkConfig, parse_spec
from netsim.env import Environment
from netsim.link import Link
from netsim.tcp import Message, TcpConnection
from netsim.udp import UdpSender

DIRECTIONS = ("down", "up")
PROTOCOLS = ("tcp", "udp")


@dataclass
class Delivery:
    """What happened to one message. Times are on the simulated clock, in seconds.

    arrival_s: when the last byte is usable at the receiver (TCP: in order); ``math.inf`` if it never completes.
    settled_s: when the receiver holds everything it will ever get (= arrival_s when complete; for an incomplete
        UDP message, its last useful arrival or the deadline; in a topology, when the fate of its last datagram
        was decided, or the deadline).
    lost_ranges: [(start, end), ...] byte ranges of the message that never arrived (end exclusive).

    A Delivery from a :class:`~netsim.topology.Topology` is tentative: reading a field brings it up to date with
    every send submitted so far (docs/netsim.md, "Topologies").
    """

    size_bytes: int
    direction: str
    protocol: str
    sent_s: float
    deadline_s: float | None = None
    _message: Message | None = field(default=None, repr=False)

    # Set by a Topology, whose results are tentative until later sends can no longer change them: brings the
    # message's results up to date before they are read. None for a Network (results are final when returned).
    _resolve: Callable[[Message], None] | None = field(default=None, repr=False, compare=False)

    def _result(self) -> Message:
        if self._resolve is not None:
            self._resolve(self._message)
        return self._message

    @property
    def arrival_s(self) -> float:
        return self._result().arrival_s

    @property
    def settled_s(self) -> float:
        return self._result().settled_s

    @property
    def delivered_bytes(self) -> int:
        return self._result().delivered_bytes

    @property
    def lost_ranges(self) -> list[tuple[int, int]]:
        return list(self._result().lost_ranges)

    @property
    def retransmissions(self) -> int:
        return self._result().retransmissions

    @property
    def complete(self) -> bool:
        return self._result().complete

    @property
    def transfer_time_s(self) -> float:
        return self.arrival_s - self.sent_s

    def to_dict(self) -> dict:
        return {"size_bytes": self.size_bytes, "direction": self.direction, "protocol": self.protocol,
                "sent_s": self.sent_s, "arrival_s": None if math.isinf(self.arrival_s) else self.arrival_s,
                "delivered_bytes": self.delivered_bytes, "lost_ranges": [list(r) for r in self.lost_ranges],
                "retransmissions": self.retransmissions, "complete": self.complete}


def check_message(size_bytes, direction: str, protocol: str, at_s, deadline_s) -> tuple[int, float, float | None]:
    """Validate one send's arguments (NetsimError naming the bad one); return (size, at_s, deadline_s) normalised."""
    if isinstance(size_bytes, bool) or not isinstance(size_bytes, numbers.Integral) and not (
            isinstance(size_bytes, numbers.Real) and math.isfinite(size_bytes) and float(size_bytes).is_integer()):
        raise NetsimError(f"message size must be a whole number of bytes, got {size_bytes!r}")
    size_bytes = int(size_bytes)
    if size_bytes <= 0:
        raise NetsimError(f"message size must be > 0 bytes, got {size_bytes}")
    if direction not in DIRECTIONS:
        raise NetsimError(f"unknown direction {direction!r} (choose from {', '.join(DIRECTIONS)})")
    if protocol not in PROTOCOLS:
        raise NetsimError(f"unknown protocol {protocol!r} (choose from {', '.join(PROTOCOLS)})")
    if not isinstance(at_s, numbers.Real) or isinstance(at_s, bool) or not math.isfinite(at_s) or at_s < 0:
        raise NetsimError(f"send time must be a finite number >= 0 s, got {at_s!r}")
    if deadline_s is not None and (not isinstance(deadline_s, numbers.Real) or isinstance(deadline_s, bool)
                                   or not deadline_s > 0):
        raise NetsimError(f"deadline must be a time budget > 0 s, got {deadline_s!r}")
    return size_bytes, float(at_s), None if deadline_s is None else float(deadline_s)


class Network:
    """Deterministic for a given (config, seed). ``send()`` calls must come in non-decreasing ``at_s``.

    A TCP message sent while an earlier one on the same connection is in flight queues behind it in the byte
    stream (head-of-line blocking) and the two are simulated together; the earlier Delivery is updated in place
    (only its loss recovery can change: the later segments' duplicate ACKs may repair a tail loss sooner).
    UDP messages and TCP segments share each link in FIFO order of sending.
    """

    def __init__(self, config: NetworkConfig, seed: int = 0):
        self.config = config.validate()
        self.seed = int(seed)
        self.env = Environment(seed=self.seed)
        self.ideal = config.is_ideal
        self.links = {d: Link(self.env, getattr(config, d), name=d) for d in DIRECTIONS}
        reverse = {"down": "up", "up": "down"}
        self.tcp = {d: TcpConnection(self.env, self.links[d], reverse_delay_s=self.links[reverse[d]].delay_s,
                                     config=config.tcp,
                                     reverse_rate_bytes_per_s=self.links[reverse[d]].rate_bytes_per_s,
                                     max_sim_time_s=config.max_sim_time_s)
                    for d in DIRECTIONS}
        self.udp = {d: UdpSender(self.env, self.links[d], reverse_delay_s=self.links[reverse[d]].delay_s,
                                 config=config.udp, max_sim_time_s=config.max_sim_time_s)
                    for d in DIRECTIONS}
        self.deliveries: list[Delivery] = []
        self._last_at_s = -math.inf

    def send(self, size_bytes: int, direction: str = "down", protocol: str = "tcp", at_s: float = 0.0,
             deadline_s: float | None = None) -> Delivery:
        """Send a message of ``size_bytes`` at ``at_s``. ``deadline_s`` is a time budget after ``at_s``: data that
        arrives later counts as lost."""
        size_bytes, at_s, deadline_s = check_message(size_bytes, direction, protocol, at_s, deadline_s)
        if at_s < self._last_at_s:
            raise NetsimError(f"send times must not decrease: {at_s} s after {self._last_at_s} s")
        self._last_at_s = at_s
        self.env.now_s = at_s
        message = Message(size_bytes=size_bytes, at_s=at_s, deadline_s=deadline_s)
        if self.ideal:
            message.arrival_s = message.settled_s = float(at_s)
            message.delivered_bytes = size_bytes
            message.complete = True
        elif protocol == "tcp":
            self.tcp[direction].put(message)
        else:
            self.udp[direction].put(message)
        delivery = Delivery(size_bytes=size_bytes, direction=direction, protocol=protocol, sent_s=float(at_s),
                            deadline_s=deadline_s, _message=message)
        self.deliveries.append(delivery)
        return delivery

    def describe(self) -> dict:
        """JSON-serialisable settings for results metadata."""
        description = self.config.to_dict()
        description["seed"] = self.seed
        return description

    def counters(self) -> dict:
        return {d: {"packets_sent": link.packets_sent, "packets_lost": link.packets_lost,
                    "packets_dropped_queue": link.packets_dropped_queue, "bytes_sent": link.bytes_sent,
                    "tcp_retransmissions": self.tcp[d].retransmissions, "tcp_timeouts": self.tcp[d].timeouts,
                    "udp_datagrams_sent": self.udp[d].datagrams_sent}
                for d, link in self.links.items()}


def make_network(spec, seed: int = 0) -> Network:
    """A network from a profile name, ``"ideal"``, an inline spec string or a dict (see :func:`parse_spec`)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise NetsimError(f"seed must be an integer, got {seed!r}")
    return Network(parse_spec(spec), seed=int(seed))
