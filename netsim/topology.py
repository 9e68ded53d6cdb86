"""Many clients, one server: each client's own access link, all of them behind the server's shared link.

Example::

    topo = make_topology(access="lan-home", server="bw=100mbps,delay=5ms,queue=1000p", clients=3, seed=0)
    d = topo.send(100_000, client=1, direction="down", protocol="tcp", at_s=0.25)
    topo.advance(0.25)          # the caller's promise: no later send has at_s < 0.25
    print(d.arrival_s)          # tentative until no later send can change it

Down (server -> client) packets cross the shared server link first, then the client's access link; up packets the
access link, then the shared link. Flows of all clients meet in the shared link's single drop-tail FIFO queue, so
TCP connections share it the way TCP does: each keeps its own window and timers and reacts to its own drops and
queueing delay. One TCP connection and one UDP sender per (client, direction). Without a server link
(``server=None``) nothing is shared: client i's directions are today's single-path :class:`~netsim.network.Network`
instances, seeded with :func:`derive_seed`.

Results are tentative: sends of different (client, direction) pairs may come in any order of time (at or after
the last ``advance``), and a message sent later in submission but earlier in simulated time changes what happened
after it. A :class:`~netsim.network.Delivery` is brought up to date when it is read. Causality is exact: a send at
time t never changes a message that settled before t, and results depend only on the sends' times, never on the
order they were submitted in. See docs/netsim.md, "Topologies".
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from netsim.config import LinkConfig, NetworkConfig, TcpConfig, UdpConfig, parse_spec
from netsim.engine import Engine, Path, TcpFlow, UdpFlow
from netsim.env import Environment
from netsim.errors import NetsimError
from netsim.link import Link
from netsim.network import DIRECTIONS, PROTOCOLS, Delivery, Network, check_message
from netsim.tcp import Message

_FINAL_FOR_GOOD = object()  # stamped on messages finalised by the committed engine: no later send can change them


def derive_seed(seed: int, client: int, direction: str) -> int:
    """The seed of client ``client``'s link (and, without a server link, its Network) in ``direction``.

    Client 0 keeps the seeds the harness has always used for its single client, ``2 * seed`` down and
    ``2 * seed + 1`` up, so one-client results stay the same. Client i > 0 gets 63 bits from numpy's
    ``SeedSequence((seed, direction, i))`` (direction 0 = down, 1 = up): deterministic, platform-independent, and
    distinct loss streams for every (seed, client, direction) in practice.
    """
    d = DIRECTIONS.index(direction)
    if client == 0:
        return 2 * int(seed) + d
    return _sequence_seed(int(seed), d, int(client))


def server_seed(seed: int, direction: str) -> int:
    """The seed of the shared server link in ``direction``: ``SeedSequence((seed, direction, 0))``'s 63 bits.
    Its random streams are named like a Network's (``down/loss``...), so ``Network(server spec,
    seed=server_seed(seed, d))`` draws the same losses on its ``d`` link."""
    return _sequence_seed(int(seed), DIRECTIONS.index(direction), 0)


def _sequence_seed(seed: int, direction: int, tag: int) -> int:
    state = np.random.SeedSequence([seed % 2 ** 63, direction, tag]).generate_state(2, np.uint32)
    return (int(state[0]) << 31) | (int(state[1]) >> 1)


class Topology:
    """C clients with their own access links sharing the server's link. Build one with :func:`make_topology`."""

    def __init__(self, access: NetworkConfig, server: NetworkConfig | None, clients: int, seed: int = 0):
        self.access = access.validate()
        self.server = server.validate() if server is not None else None
        self.clients = int(clients)
        self.seed = int(seed)
        self.frontier_s = 0.0                  # the last advance(): no send may come earlier
        self._last_at_s: dict = {}             # (client, direction) -> last send time
        self._counts: dict = {}                # flow id -> messages submitted
        if self.server is None:
            # Nothing shared: each (client, direction) is an independent single-path Network.
            self._networks = {(i, d): Network(self.access, seed=derive_seed(self.seed, i, d))
                              for i in range(self.clients) for d in DIRECTIONS}
            return
        self._networks = None
        self._build_engine()
        self._tentative: Engine | None = None

    # -- construction ------------------------------------------------------------------------------------------
    def _build_engine(self) -> None:
        access, server = self.access, self.server
        links: list[Link] = []

        def make(config: LinkConfig, seed: int, direction: str) -> Link | None:
            link = Link(Environment(seed=seed), config, name=direction)
            links.append(link)
            return None if config.is_ideal else link  # an ideal link is no hop at all

        # links[0], links[1]: the server link down and up; links[2 + 2i], links[3 + 2i]: client i's down and up.
        shared = {d: make(getattr(server, d), server_seed(self.seed, d), d) for d in DIRECTIONS}
        flows = []
        merged = self.clients > 1  # the shared link merges several access links (up) when there are several
        for i in range(self.clients):
            own = {d: make(getattr(access, d), derive_seed(self.seed, i, d), d) for d in DIRECTIONS}
            paths = {
                "down": _path([(shared["down"], False), (own["down"], False)], [own["up"], shared["up"]]),
                "up": _path([(own["up"], False), (shared["up"], merged)], [shared["down"], own["down"]]),
            }
            for d in DIRECTIONS:
                flows.append(TcpFlow(_fid(i, d, "tcp"), paths[d], access.tcp, access.max_sim_time_s))
                flows.append(UdpFlow(_fid(i, d, "udp"), paths[d], access.udp, access.max_sim_time_s))
        self._committed = Engine(links, flows, salt=server_seed(self.seed, "down"))
        self._committed.ident = _FINAL_FOR_GOOD

    # -- the API -----------------------------------------------------------------------------------------------
    def send(self, size_bytes: int, client: int = 0, direction: str = "down", protocol: str = "tcp",
             at_s: float = 0.0, deadline_s: float | None = None) -> Delivery:
        """Send a message of ``size_bytes`` between the server and ``client`` at ``at_s``; ``deadline_s`` is a
        time budget after ``at_s`` (later data counts as lost). The Delivery is tentative until no later send can
        change it (see the module docstring); reading it brings it up to date."""
        if isinstance(client, bool) or not isinstance(client, numbers.Integral):
            raise NetsimError(f"client must be an integer index, got {client!r}")
        if not 0 <= client < self.clients:
            raise NetsimError(f"client {client} out of range: this topology has clients 0..{self.clients - 1}")
        size_bytes, at_s, deadline_s = check_message(size_bytes, direction, protocol, at_s, deadline_s)
        if at_s < self.frontier_s:
            raise NetsimError(f"send time {at_s} s is before the last advance({self.frontier_s}) s")
        pair = (int(client), direction)
        last = self._last_at_s.get(pair, -math.inf)
        if at_s < last:
            raise NetsimError(f"send times of client {client} {direction} must not decrease: {at_s} s after {last} s")
        self._last_at_s[pair] = at_s
        if self._networks is not None:
            return self._networks[pair].send(size_bytes, direction=direction, protocol=protocol, at_s=at_s,
                                             deadline_s=deadline_s)
        message = Message(size_bytes=size_bytes, at_s=at_s, deadline_s=deadline_s)
        message._final_by = None
        fid = _fid(pair[0], direction, protocol)
        index = self._counts.get(fid, 0)
        self._counts[fid] = index + 1
        self._committed.add_message(fid, index, message)
        tentative = self._tentative
        if tentative is not None:
            if tentative.accepts(fid, index, at_s):
                tentative.add_message(fid, index, message)
            else:
                self._tentative = None  # it has simulated past this send: start again from the checkpoint
        return Delivery(size_bytes=size_bytes, direction=direction, protocol=protocol, sent_s=at_s,
                        deadline_s=deadline_s, _message=message, _resolve=self._resolve)

    def advance(self, t_s: float) -> None:
        """The caller's promise that no later send has ``at_s < t_s``: the simulation up to ``t_s`` becomes final
        (the checkpoint moves there) and the messages settled before it are never simulated again."""
        if isinstance(t_s, bool) or not isinstance(t_s, numbers.Real) or not math.isfinite(t_s) or t_s < 0:
            raise NetsimError(f"advance time must be a finite number >= 0 s, got {t_s!r}")
        t_s = float(t_s)
        if t_s <= self.frontier_s:
            return  # an earlier promise already covers it
        self.frontier_s = t_s
        if self._networks is not None:
            return
        tentative = self._tentative
        if tentative is not None and tentative.now < t_s:
            # The tentative run holds every send and has not passed t_s: run it to t_s and make it the checkpoint,
            # instead of simulating the interval again from the old one (the next read copies it).
            tentative.run(until_s=t_s)
            for message in tentative.finalized:
                message._final_by = _FINAL_FOR_GOOD
            tentative.ident = _FINAL_FOR_GOOD
            self._committed = tentative
            self._tentative = None
        else:
            self._committed.run(until_s=t_s)
        self._committed.finalized = []

    def describe(self) -> dict:
        """JSON-serialisable settings for results metadata."""
        return {"clients": self.clients, "seed": self.seed, "access": self.access.to_dict(),
                "server": None if self.server is None else self.server.to_dict(),
                "seeds": "client i, direction d: derive_seed(seed, i, d) (client 0: 2*seed down, 2*seed+1 up); "
                         "server link: server_seed(seed, d); see netsim.topology"}

    def counters(self) -> dict:
        """Per link: packets sent, lost on the wire, dropped by the queue, bytes; per (client, direction): TCP
        retransmissions and timeouts, UDP datagrams. Simulates every message sent so far to its end."""
        if self._networks is not None:
            return {"server": None,
                    "clients": [{d: self._networks[(i, d)].counters()[d] for d in DIRECTIONS}
                                for i in range(self.clients)]}
        engine = self._current()
        engine.run()
        flows = engine.flows

        def link_counters(link: Link) -> dict:
            return {"packets_sent": link.packets_sent, "packets_lost": link.packets_lost,
                    "packets_dropped_queue": link.packets_dropped_queue, "bytes_sent": link.bytes_sent}

        server = {}
        for k, d in enumerate(DIRECTIONS):
            server[d] = link_counters(engine.links[k])
        clients = []
        for i in range(self.clients):
            entry = {}
            for k, d in enumerate(DIRECTIONS):
                counters = link_counters(engine.links[2 + 2 * i + k])
                tcp = flows[_fid(i, d, "tcp")]
                udp = flows[_fid(i, d, "udp")]
                counters.update(tcp_retransmissions=tcp.retransmissions, tcp_timeouts=tcp.timeouts,
                                udp_datagrams_sent=udp.datagrams_sent)
                entry[d] = counters
            clients.append(entry)
        return {"server": server, "clients": clients}

    # -- tentative results -------------------------------------------------------------------------------------
    def _current(self) -> Engine:
        """The tentative engine: the checkpoint's copy, holding every send so far."""
        if self._tentative is None:
            self._tentative = self._committed.clone()
        return self._tentative

    def _resolve(self, message: Message) -> None:
        final_by = message._final_by
        if final_by is _FINAL_FOR_GOOD:
            return
        engine = self._current()
        if final_by is engine.ident:
            return
        engine.run(stop=message)
        if message._final_by is not engine.ident:  # cannot happen: every message ends (cap, deadline, arrival)
            raise RuntimeError("netsim topology: a message was left unfinished")


def _fid(client: int, direction: str, protocol: str) -> int:
    """Flow id: the canonical order of flows at equal times (client, then direction, then protocol)."""
    return 4 * client + 2 * DIRECTIONS.index(direction) + PROTOCOLS.index(protocol)


def _path(hops: list[tuple[Link | None, bool]], reverse: list[Link | None]) -> Path:
    kept = [(link, merge) for link, merge in hops if link is not None]
    return Path([link for link, _ in kept], [merge for _, merge in kept], [r for r in reverse if r is not None])


def _transport_free(config: NetworkConfig) -> bool:
    return (config.tcp == TcpConfig() and config.udp == UdpConfig()
            and config.max_sim_time_s == NetworkConfig().max_sim_time_s)


def make_topology(access="lan-home", server=None, clients: int = 1, seed: int = 0) -> Topology:
    """A topology of ``clients`` clients, each behind an ``access`` link, sharing the ``server`` link.

    ``access`` and ``server``: a profile name, an inline spec or a dict, as :func:`netsim.make_network` takes.
    ``server=None``: no shared bottleneck. Transport options (``cc``, ``iw``, ``sack``, ``pacing``, ...) and
    ``max_sim_time_s`` belong in ``access``: they are the endpoints' settings, the server spec describes a link.
    """
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise NetsimError(f"seed must be an integer, got {seed!r}")
    if isinstance(clients, bool) or not isinstance(clients, numbers.Integral) or clients < 1:
        raise NetsimError(f"clients must be an integer >= 1, got {clients!r}")
    access_config = parse_spec(access)
    server_config = None if server is None else parse_spec(server)
    if server_config is not None and not _transport_free(server_config):
        raise NetsimError("server spec sets transport options (cc, iw, sack, pacing, max_sim_time_s, ...): "
                          "put them in the access spec, they apply to every connection")
    return Topology(access_config, server_config, int(clients), seed=int(seed))


if __name__ == "__main__":
    # Two clients behind home routers share a 20 Mbit/s server link: 5 MB each, 10 MB together, which take at least
    # 10 MB * 1500/1460 * 8 / 20 Mbit/s = 4.1 s however the link is shared.
    server = "bw=20mbps,delay=5ms,queue=200p"
    shared = make_topology(access="lan-home", server=server, clients=2, seed=0)
    first = shared.send(5_000_000, client=0, direction="down", protocol="tcp", at_s=0.0)
    second = shared.send(5_000_000, client=1, direction="down", protocol="tcp", at_s=0.0)
    alone = make_topology(access="lan-home", server=server, clients=1, seed=0).send(5_000_000, client=0, at_s=0.0)
    print(f"5 MB alone: {alone.arrival_s:.2f} s; shared: client 0 {first.arrival_s:.2f} s, "
          f"client 1 {second.arrival_s:.2f} s")
