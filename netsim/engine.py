"""The joint engine behind :mod:`netsim.topology`: many flows over many links on one simulated clock.

The single-path engine (:mod:`netsim.tcp`, :mod:`netsim.udp`) lets each transport commit its packets to its link
as soon as it sends them, which is exact for one flow and only approximate for several. Here every flow (one TCP
connection or one UDP sender) is a state machine driven by a heap of events, so that the packets of all flows
reach each link in time order and a shared drop-tail queue sees them interleaved as they really are.

Events (a tuple ``(time, kind, tie-break, flow id, number, data)``; the heap orders them by that key):

- ``HOP``: a packet reaches a link where the packets of several flows merge (the shared server link in the up
  direction, fed by every client's access link);
- ``WAKE``: a flow's own next event (an ACK reaching the sender, the retransmission or delayed-ACK timer, the
  next paced datagram), one valid entry per flow at a time;
- ``MSG``: the application hands a message to a flow;
- ``FINAL``: a message's results can no longer change (its arrival, or its deadline, has passed); they are
  written into its :class:`~netsim.tcp.Message`.

A link is a FIFO recurrence, so a packet's departure and arrival are computed when it is offered
(:meth:`Link.transmit`); offers to a link only need to come in time order. The first link of a path is offered
at the sending event's time, which the heap keeps in order. A later link that only this path's previous link feeds
(the client's access link after the shared link, down) receives packets in the order that FIFO link delivers them,
so it is offered at once as well; a link fed by several links (the shared link, up) gets a ``HOP`` event.

Every key is canonical: it depends on times, flow ids and per-flow counters only, never on the order in which
messages were submitted. Results therefore depend only on the messages' send times (and the seed), and an
engine copied at any point (:meth:`Engine.clone`) and run on gives the same results as one that never stopped.

A copy is copy-on-write: the two engines share every flow and link, and either one copies a flow or a link only
when it is about to change it (the first event of that flow, the first packet offered to that link). So a
checkpoint's copy costs what the simulation after it touches, not what the topology holds: the idle clients' flows
and access links are never copied. Flows reach their links through the engine (a path holds link numbers), so a
flow sees its own engine's links whoever copied them.

TCP follows :mod:`netsim.tcp` rule for rule (same :class:`~netsim.tcp._CongestionState`, SACK scoreboard,
PRR, RTO, slow-start restart; tests/netsim/test_topology.py checks that one flow over one link gives the
single-path engine's results). Two differences, both where the single-path engine approximates: data written
while segments are in flight is sent at once if the window allows (the single-path engine waits for the next
ACK), and ``retransmissions`` counts the message's segments resent until it settled (spurious resends after its
last byte arrived are not counted, so that a later send can never change a settled message).
"""

from __future__ import annotations

import heapq
import math
from bisect import bisect_right
from collections import deque

from netsim.config import TCP_HEADER_BYTES, UDP_HEADER_BYTES, TcpConfig, UdpConfig
from netsim.link import Link
from netsim.tcp import ACK_BYTES, Message, _CongestionState, rto_update

INF = math.inf
HOP, WAKE, MSG, FINAL = 0, 1, 2, 3
_MASK64 = (1 << 64) - 1


def tiebreak(salt: int, t: float, fid: int) -> int:
    """The order of different flows' events at exactly the same time: a hash of (time, flow, seed).

    Sends of several clients at the same instant are common (frames go out at the same frame times). A fixed order
    (client 0 first) would always let the same client's packets into a shared queue first, a systematic bias no
    real server has; this order is canonical (it depends on nothing but the time, the flow and the seed) and
    changes from one instant to the next. ``hash`` of a float is defined arithmetically by Python (stable across
    runs and platforms); the mixing is SplitMix64's finaliser.
    """
    x = (hash(t) ^ salt ^ (fid * 0x9E3779B97F4A7C15)) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


class Path:
    """The links a flow's packets cross, in order, and what its ACKs (or NACKs) take on the way back.

    ``merges[k]``: link k is fed by other links besides ``hops[k - 1]`` (packets reach it through HOP events).
    ACKs are not simulated packet by packet: like the single-path engine they take the reverse links' delays and
    serialisation of 40 bytes, are never lost and never queue (docs/netsim.md, "TCP model").

    A path holds only constants. The :class:`Engine` it is given to binds it (:meth:`bind`): ``hop_ids`` are then
    the numbers of its links in ``engine.links``, where the engine keeps the current object of each link (a copy
    after copy-on-write), and the Link objects themselves are dropped so that nothing can reach a stale one.
    """

    def __init__(self, hops: list[Link], merges: list[bool], reverse: list[Link]):
        self.hops = hops
        self.hop_ids: list[int] | None = None
        self.merges = merges
        # A link is offered immediately unless several links feed it, or the previous one may reorder packets
        # (then its output is not in time order).
        self.immediate = [k == 0 or (not merges[k] and not hops[k - 1].config.reorder) for k in range(len(hops))]
        self.reverse = reverse
        self.delay_s = sum(h.delay_s for h in hops)
        self.header_one_way_s = sum(h.delay_s + TCP_HEADER_BYTES / h.rate_bytes_per_s for h in hops)
        self.ack_delay_s = sum(r.delay_s + ACK_BYTES / r.rate_bytes_per_s for r in reverse)
        self.reverse_delay_s = sum(r.delay_s for r in reverse)
        self.rate_bytes_per_s = min((h.rate_bytes_per_s for h in hops), default=INF)
        self.mtu_bytes = min((h.config.mtu_bytes for h in hops), default=1500)
        self.hop_rates = [h.rate_bytes_per_s for h in hops]

    def bind(self, numbers: dict) -> None:
        """Refer to the links by their numbers in the engine (``numbers``: id of a link -> its number). A path
        belongs to one engine (and to the copies of that engine)."""
        if self.hop_ids is not None:
            raise ValueError("this path is bound to another engine already")
        self.hop_ids = [numbers[id(h)] for h in self.hops]
        self.hops = self.reverse = None

    def serialisation_s(self, wire_bytes: int) -> float:
        return sum(wire_bytes / rate for rate in self.hop_rates)


class Engine:
    """Links, flows and the event heap. ``run()`` processes events; ``clone()`` is an independent copy.

    ``links[k]`` and ``flows[fid]`` are the current objects; an object whose ``_owner`` is not this engine's
    ``owner`` may be shared with a copy of the engine and is copied before it changes (copy-on-write; counted in
    ``flows_copied`` and ``links_copied``).
    """

    def __init__(self, links: list[Link], flows: list, salt: int = 0):
        self.links = list(links)
        self.flows = list(flows)
        self.salt = salt & _MASK64  # from the seed: the tie-break order of simultaneous events
        self.heap: list = []
        self.now = -INF
        self.last_event = (-INF,)   # the last event processed: a message may join only after it
        self.ident = object()       # stamped on the messages this engine finalises
        self.finalized: list[Message] = []
        self.owner = object()       # stamped on the links and flows this engine alone holds
        self.flows_copied = 0
        self.links_copied = 0
        numbers = {id(link): k for k, link in enumerate(self.links)}
        bound: set = set()
        for link in self.links:
            link._owner = self.owner
        for fid, flow in enumerate(self.flows):
            if flow.fid != fid:
                raise ValueError(f"flow {flow.fid} at position {fid}: flows must be listed in the order of their ids")
            flow._owner = self.owner
            if id(flow.path) not in bound:  # flows of one (client, direction) share their path
                flow.path.bind(numbers)
                bound.add(id(flow.path))

    # -- input ---------------------------------------------------------------------------------------------------
    def add_message(self, fid: int, index: int, message: Message) -> None:
        at_s = message.at_s
        heapq.heappush(self.heap, (at_s, MSG, tiebreak(self.salt, at_s, fid), fid, index, message))

    def accepts(self, fid: int, index: int, at_s: float) -> bool:
        """Whether a message can still join without changing what this engine has already simulated."""
        return (at_s, MSG, tiebreak(self.salt, at_s, fid), fid, index) > self.last_event[:5]

    # -- packets -------------------------------------------------------------------------------------------------
    def transmit(self, flow, t: float, wire_bytes: int, payload, keep_order: bool, hop: int = 0) -> None:
        """Offer a packet to ``flow``'s path at link ``hop`` at time ``t``; the flow's ``deliver`` learns its
        arrival time at the far end, or None with the time it was dropped."""
        path = flow.path
        hop_ids = path.hop_ids
        immediate = path.immediate
        links = self.links
        owner = self.owner
        last = len(hop_ids) - 1
        while True:
            link = links[hop_ids[hop]]
            if link._owner is not owner:
                link = self._own_link(hop_ids[hop])
            arrival = link.transmit(t, wire_bytes, None, keep_order)
            if arrival is None:
                flow.deliver(self, payload, None, t)
                return
            if hop == last:
                flow.deliver(self, payload, arrival, t)
                return
            hop += 1
            if immediate[hop]:
                t = arrival
                continue
            flow.packet_number += 1
            heapq.heappush(self.heap, (arrival, HOP, tiebreak(self.salt, arrival, flow.fid), flow.fid,
                                       flow.packet_number, (hop, wire_bytes, payload, keep_order)))
            return

    # -- the loop ------------------------------------------------------------------------------------------------
    def run(self, until_s: float = INF, stop: Message | None = None) -> None:
        """Process events earlier than ``until_s``, or until ``stop`` has been finalised by this engine."""
        heap = self.heap
        flows = self.flows
        pop = heapq.heappop
        ident = self.ident
        owner = self.owner
        while heap:
            event = heap[0]
            t = event[0]
            if t >= until_s:
                break
            pop(heap)
            self.now = t
            self.last_event = event
            kind = event[1]
            fid = event[3]
            flow = flows[fid]
            if kind == WAKE:
                if event[4] != flow.token:
                    continue  # superseded by a later schedule()
            elif kind == FINAL and event[4] not in flow.states:
                continue  # already finalised (on_final would do nothing)
            if flow._owner is not owner:
                flow = self._own_flow(fid)
            if kind == WAKE:
                flow.wake_s = INF
                flow.on_wake(self, t)
                flow.schedule(self)
            elif kind == HOP:
                hop, wire_bytes, payload, keep_order = event[5]
                self.transmit(flow, t, wire_bytes, payload, keep_order, hop)
                flow.schedule(self)
            elif kind == MSG:
                flow.on_message(self, t, event[4], event[5])
                flow.schedule(self)
            else:
                flow.on_final(self, t, event[4])
            if stop is not None and stop._final_by is ident:
                return

    def finalize(self, message: Message) -> None:
        message._final_by = self.ident
        self.finalized.append(message)

    def clone(self) -> "Engine":
        """An independent copy. It copies the event heap and two lists of references, nothing else: from here on
        both engines share every link and flow, and either copies one just before it changes it (neither owns
        them any more), so the cost of a copy follows what is simulated after it, not the number of flows."""
        other = Engine.__new__(Engine)
        other.links = list(self.links)
        other.flows = list(self.flows)
        other.heap = list(self.heap)  # events are immutable tuples (messages are only read)
        other.salt = self.salt
        other.now = self.now
        other.last_event = self.last_event
        other.ident = object()
        other.finalized = []
        other.owner = object()
        other.flows_copied = other.links_copied = 0
        self.owner = object()  # what this engine held is shared now: it copies before writing too
        return other

    def _own_flow(self, fid: int):
        flow = self.flows[fid].clone()
        flow._owner = self.owner
        self.flows[fid] = flow
        self.flows_copied += 1
        return flow

    def _own_link(self, number: int) -> Link:
        link = self.links[number].copy()
        link._owner = self.owner
        self.links[number] = link
        self.links_copied += 1
        return link


class _Flow:
    """What every flow has: an id (its place in the canonical order), a path and one pending wake-up."""

    def __init__(self, fid: int, path: Path, max_sim_time_s: float):
        self.fid = fid
        self.path = path
        self.max_sim_time_s = max_sim_time_s
        self.wake_s = INF       # time of the valid WAKE entry in the heap (INF: none)
        self.token = 0          # number of the valid WAKE entry
        self.packet_number = 0  # numbers this flow's HOP events
        self.states: dict = {}  # message number -> per-message state, until the message is finalised
        self._owner = None      # the Engine.owner of the engine that may change this flow in place (copy-on-write)

    def schedule(self, engine: Engine) -> None:
        t = self.next_event_s()
        if t != self.wake_s:
            self.wake_s = t
            self.token += 1
            if t < INF:
                heapq.heappush(engine.heap, (t, WAKE, tiebreak(engine.salt, t, self.fid), self.fid, self.token, None))


# ---------------------------------------------------------------------------------------------------------------
# TCP


class _TcpMessage:
    """A message on a TCP flow: its segments [start, end) in the current busy period, when its last byte was
    in order at the receiver, and its retransmissions so far."""

    __slots__ = ("message", "index", "start", "end", "done_s", "retransmissions", "deadline_abs_s")

    def __init__(self, message: Message, index: int, start: int, end: int):
        self.message = message
        self.index = index
        self.start = start
        self.end = end
        self.done_s = INF
        self.retransmissions = 0
        self.deadline_abs_s = message.at_s + message.deadline_s if message.deadline_s is not None else INF

    def copy(self) -> "_TcpMessage":
        other = _TcpMessage.__new__(_TcpMessage)
        other.message = self.message
        other.index = self.index
        other.start = self.start
        other.end = self.end
        other.done_s = self.done_s
        other.retransmissions = self.retransmissions
        other.deadline_abs_s = self.deadline_abs_s
        return other


class TcpFlow(_Flow):
    """One direction of a persistent TCP connection, rule for rule the sender and receiver of
    :meth:`netsim.tcp.TcpConnection._run` (see that module for the RFCs), as an event-driven state machine.

    Counters: ``segments_sent``, ``retransmissions``, ``timeouts``, ``fast_retransmits``.
    """

    def __init__(self, fid: int, path: Path, config: TcpConfig, max_sim_time_s: float):
        super().__init__(fid, path, max_sim_time_s)
        self.config = config
        self.mss = path.mtu_bytes - TCP_HEADER_BYTES
        self.ack_delay = path.ack_delay_s
        self.rwnd = max(1, int(config.receive_window_bytes // self.mss))
        self.min_rto = config.min_rto_ms * 1e-3
        self.max_rto = config.max_rto_ms * 1e-3
        self.use_sack = config.sack
        self.delack = config.delayed_ack
        self.delack_timeout = config.delayed_ack_timeout_ms * 1e-3
        # The connection (persists across busy periods).
        self.established = False
        self.cc = _CongestionState(config)
        self.srtt = None
        self.rttvar = 0.0
        self.rto = config.initial_rto_ms * 1e-3
        self.min_rtt = INF
        self.last_ack_s = -INF   # the single-path engine's last_activity_s: slow-start restart measures from it
        self.segments_sent = 0
        self.retransmissions = 0
        self.timeouts = 0
        self.fast_retransmits = 0
        # Handshake (count_handshake=on): 0 = none pending, 1 = SYN in flight, 2 = SYN-ACK on its way, 3 = SYN lost.
        self.hs = 0
        self.syn_sent_s = 0.0
        self.syn_start_s = 0.0
        self.syn_timeout = 0.0
        self.syn_event_s = INF
        self.handshake_rtt = 0.0
        # The busy period (segments numbered from 0; messages that arrive while it lasts join it).
        self.period = 0
        self.active = False
        self._reset_period()

    def _reset_period(self) -> None:
        self.period += 1
        self.pmsgs: list[_TcpMessage] = []   # messages of this period, in stream order
        self.pmsg_end: list[int] = []        # their end segments
        self.seg_bytes: list[int] = []
        self.seg_msg: list[int] = []         # position in pmsgs
        self.send_time: list[float] = []
        self.retransmitted = bytearray()
        self.received = bytearray()
        self.sacked = bytearray()
        self.retx_episode: list[int] = []
        self.n = 0
        self.ackq: deque = deque()
        self.una = self.nxt = self.high_tx = self.rcv_nxt = self.next_done = 0
        self.dupacks = 0
        self.in_recovery = False
        self.recover = -1
        self.rto_deadline = INF
        self.pending_ack_s = INF
        self.pending_cum = 0
        self.pending_seg = 0
        self.advances: list = []          # (arrival time, rcv_nxt) whenever in-order data reached the receiver
        self.advance_times: list = []
        self.sacked_count = 0
        self.highest_sacked = -1
        self.episode = 0
        self.retx_out: deque = deque()
        self.hole = 0
        self.prr_delivered = 0
        self.prr_out = 0
        self.recover_fs = 1
        self.cap_s = INF

    def clone(self) -> "TcpFlow":
        """An independent copy (the engine's copy-on-write). Between busy periods the period's containers and
        message states are only read (a new period replaces them), so an idle flow's copy shares them."""
        other = object.__new__(TcpFlow)
        other.__dict__.update(self.__dict__)
        other.cc = self.cc.copy()
        if not self.active:
            other.states = dict(self.states)
            return other
        copies = {}
        pmsgs = []
        for state in self.pmsgs:
            twin = state.copy()
            copies[id(state)] = twin
            pmsgs.append(twin)
        other.pmsgs = pmsgs
        states = {}
        for index, state in self.states.items():
            twin = copies.get(id(state))
            states[index] = twin if twin is not None else state.copy()  # an earlier period's, awaiting FINAL
        other.states = states
        other.pmsg_end = self.pmsg_end[:]
        other.seg_bytes = self.seg_bytes[:]
        other.seg_msg = self.seg_msg[:]
        other.send_time = self.send_time[:]
        other.retx_episode = self.retx_episode[:]
        other.advances = self.advances[:]
        other.advance_times = self.advance_times[:]
        other.retransmitted = self.retransmitted[:]
        other.received = self.received[:]
        other.sacked = self.sacked[:]
        other.ackq = self.ackq.copy()
        other.retx_out = self.retx_out.copy()
        return other

    # -- events --------------------------------------------------------------------------------------------------
    def next_event_s(self) -> float:
        if not self.active:
            return INF
        if self.hs:
            return self.syn_event_s
        if self.ackq:
            t = self.ackq[0][0]
        elif self.pending_ack_s < INF:
            t = self.pending_ack_s + self.delack_timeout + self.ack_delay
        else:
            t = INF
        if self.una < self.nxt and self.rto_deadline < t:
            t = self.rto_deadline
        # The single-path engine stops a busy period whose next event lies beyond the cap (max_sim_time_s).
        return t if t <= self.cap_s else self.cap_s

    def on_message(self, engine: Engine, t: float, index: int, message: Message) -> None:
        if not self.path.hop_ids:  # an ideal path: delivered at once, as Network does for the ideal profile
            _finish(engine, message, arrival_s=t, delivered=message.size_bytes, lost=[], retransmissions=0)
            return
        mss = self.mss
        full, rest = divmod(message.size_bytes, mss)
        count = full + (1 if rest else 0)
        starting = not self.active
        if starting:
            self._reset_period()
            self.active = True
        start = self.n
        state = _TcpMessage(message, index, start, start + count)
        self.states[index] = state
        if state.deadline_abs_s < INF:
            heapq.heappush(engine.heap, (state.deadline_abs_s, FINAL, 0, self.fid, index, None))
        # Each message starts a new segment (TCP_NODELAY, no Nagle).
        self.seg_bytes.extend([mss] * full)
        if rest:
            self.seg_bytes.append(rest)
        self.seg_msg.extend([len(self.pmsgs)] * count)
        self.pmsgs.append(state)
        self.pmsg_end.append(start + count)
        self.send_time.extend([0.0] * count)
        self.retransmitted.extend(bytes(count))
        self.received.extend(bytes(count))
        self.sacked.extend(bytes(count))
        self.retx_episode.extend([0] * count)
        self.n = start + count
        if starting:
            self._start_period(engine, t)
        elif not self.hs:
            self._send_window(engine, t)

    def _start_period(self, engine: Engine, t: float) -> None:
        config = self.config
        if not self.established:
            # SYN out, SYN-ACK back: the round trip is the first RTT sample (RFC 6298 2.2). Uncharged, the
            # connection was set up before the session and nothing is sent.
            if config.count_handshake:
                self.syn_start_s = t
                self.syn_timeout = config.initial_rto_ms * 1e-3
                self._send_syn(engine, t)
                return
            self._rtt_sample(self.path.header_one_way_s + self.ack_delay)
            self.established = True
        elif config.slow_start_restart and t - self.last_ack_s > self.rto:
            self.cc.cwnd = min(self.cc.cwnd, self.cc.iw)  # RFC 5681 4.1 restart window
        self._open(engine, t)

    def _open(self, engine: Engine, t: float) -> None:
        self.cap_s = t + self.max_sim_time_s
        self.last_ack_s = t
        self._send_window(engine, t)

    def _send_syn(self, engine: Engine, t: float) -> None:
        self.hs = 1
        self.syn_sent_s = t
        self.syn_event_s = INF
        engine.transmit(self, t, TCP_HEADER_BYTES, (self.period, -1), True)

    def _syn_fate(self, arrival: float | None, t: float) -> None:
        if arrival is not None:
            self.hs = 2
            self.handshake_rtt = (arrival - self.syn_sent_s) + self.ack_delay
            self.syn_event_s = self.syn_sent_s + self.handshake_rtt
        elif self.syn_sent_s - self.syn_start_s > self.max_sim_time_s:
            # Past the time cap: give up resending and proceed, as the single-path engine does.
            self.hs = 2
            self.handshake_rtt = self.path.delay_s + self.ack_delay
            self.syn_event_s = self.syn_sent_s + self.handshake_rtt
        else:
            # Resent after the initial RTO, doubling (RFC 6298 5.7).
            self.hs = 3
            self.syn_event_s = max(self.syn_sent_s + self.syn_timeout, t)

    def on_wake(self, engine: Engine, t: float) -> None:
        if not self.active:
            return
        if self.hs:
            if t < self.syn_event_s:
                return
            if self.hs == 2:
                self.hs = 0
                self._rtt_sample(self.handshake_rtt)
                self.established = True
                self._open(engine, t)
            elif self.hs == 3:
                self.syn_timeout *= 2.0
                self._send_syn(engine, t)
            return
        ackq = self.ackq
        if ackq:
            next_ack_s, cum, ack_seg = ackq[0]
            from_queue = True
        elif self.pending_ack_s < INF:
            next_ack_s = self.pending_ack_s + self.delack_timeout + self.ack_delay
            cum, ack_seg = self.pending_cum, self.pending_seg
            from_queue = False
        else:
            next_ack_s = INF
        timer_s = self.rto_deadline if self.una < self.nxt else INF
        event_s = next_ack_s if next_ack_s < timer_s else timer_s
        if event_s > self.cap_s:
            if t >= self.cap_s:
                self._abandon(engine)
            return
        if event_s > t:
            return
        if next_ack_s <= timer_s:
            if from_queue:
                ackq.popleft()
            else:
                self.pending_ack_s = INF
            self._on_ack(engine, t, cum, ack_seg)
            if self.una >= self.n:
                self._end_period()
                return
        else:
            self._on_timeout(engine, t)
        self._send_window(engine, t)

    def _send_window(self, engine: Engine, t: float) -> None:
        """Send what the window allows (outside recovery: flight = nxt - una), then arm the timer."""
        if not self.in_recovery:
            cc = self.cc
            window = cc.cwnd if cc.cwnd < self.rwnd else self.rwnd
            sacked = self.sacked
            while self.nxt < self.n and self.nxt - self.una + 1 <= window:
                if sacked[self.nxt]:
                    self.nxt += 1  # after a timeout, skip what the receiver already reported
                    continue
                self._send(engine, self.nxt, t)
                self.nxt += 1
        if self.nxt > self.una and self.rto_deadline == INF:
            self.rto_deadline = t + self.rto

    def _end_period(self) -> None:
        self.active = False
        self.rto_deadline = INF

    def _abandon(self, engine: Engine) -> None:
        """The busy period ran past the time cap: what is not in order at the receiver never arrives."""
        for state in self.pmsgs:
            if state.index in self.states:
                del self.states[state.index]
                self._finish_tcp(engine, state, cut=True)
        self.active = False
        self._reset_period()

    # -- the sender ----------------------------------------------------------------------------------------------
    def _send(self, engine: Engine, i: int, now: float) -> None:
        self.segments_sent += 1
        self.send_time[i] = now
        if i < self.high_tx:
            self.retransmissions += 1
            self.retransmitted[i] = 1
            state = self.pmsgs[self.seg_msg[i]]
            # Counted until the message settles (its last byte in order, or its deadline).
            if now <= state.done_s and now <= state.deadline_abs_s:
                state.retransmissions += 1
        else:
            self.high_tx = i + 1
        engine.transmit(self, now, self.seg_bytes[i] + TCP_HEADER_BYTES, (self.period, i), True)

    def _rtt_sample(self, rtt_s: float) -> None:
        self.min_rtt = min(self.min_rtt, rtt_s)
        self.srtt, self.rttvar, self.rto = rto_update(self.srtt, self.rttvar, rtt_s, self.min_rto, self.max_rto)

    def _on_ack(self, engine: Engine, t: float, cum: int, ack_seg: int) -> None:
        cc = self.cc
        self.last_ack_s = t
        newly_sacked = 0
        sacked = self.sacked
        una = self.una
        if self.use_sack and ack_seg >= cum and ack_seg >= una and not sacked[ack_seg]:
            sacked[ack_seg] = 1
            self.sacked_count += 1
            newly_sacked = 1
            if ack_seg > self.highest_sacked:
                self.highest_sacked = ack_seg
        if cum > una:
            acked = cum - una
            if not self.retransmitted[cum - 1]:  # Karn's rule: no samples from retransmitted segments
                # RFC 6298 2.3 with the 2.4-2.5 clamps; the same arithmetic, in the same order, as netsim.tcp.
                rtt = t - self.send_time[cum - 1]
                if rtt < self.min_rtt:
                    self.min_rtt = rtt
                srtt = self.srtt
                delta = srtt - rtt
                rttvar = 0.75 * self.rttvar + 0.25 * (delta if delta > 0 else -delta)
                srtt = 0.875 * srtt + 0.125 * rtt
                self.rttvar = rttvar
                self.srtt = srtt
                rto = srtt + (4.0 * rttvar if rttvar > 0.00025 else 0.001)
                self.rto = self.min_rto if rto < self.min_rto else (self.max_rto if rto > self.max_rto else rto)
            if self.sacked_count:
                for s in range(una, cum):
                    self.sacked_count -= sacked[s]
            self.una = una = cum
            if self.nxt < una:
                self.nxt = una  # a go-back-N resend was overtaken by the receiver's buffered data
            self.dupacks = 0
            if self.in_recovery:
                if una > self.recover:
                    # Full ACK: leave recovery at ssthresh (RFC 6582 3.2 step 3, RFC 6675 5).
                    cc.cwnd = cc.ssthresh
                    self.in_recovery = False
                elif self.use_sack:
                    self._prr_step(engine, t, acked + newly_sacked)
                else:
                    # Partial ACK: resend the next hole, deflate by the amount acked, add one.
                    self._send(engine, una, t)
                    cc.cwnd = max(cc.cwnd - acked + 1.0, 1.0)
            else:
                # Window growth (slow start, NewReno or CUBIC), limited to the window in use (RFC 7661 spirit).
                cc.on_ack(acked, t, self.min_rtt)
            self.rto_deadline = t + self.rto if una < self.nxt else INF  # RFC 6298 5.3
        elif self.nxt > una:
            self.dupacks += 1
            dupacks = self.dupacks
            if self.in_recovery:
                if self.use_sack:
                    self._prr_step(engine, t, newly_sacked)
                else:
                    cc.cwnd += 1.0  # window inflation, RFC 6582 3.2 step 4
            elif dupacks < 3:
                # Limited transmit (RFC 3042): a new segment for each of the first two duplicate ACKs.
                nxt = self.nxt
                if nxt < self.n and nxt - una < int(cc.cwnd) + dupacks and nxt - una < self.rwnd:
                    self._send(engine, nxt, t)
                    self.nxt = nxt + 1
            elif dupacks == 3 and una > self.recover:
                # Fast retransmit (RFC 5681 3.2); "una > recover" avoids a second reduction for losses of the same
                # window (RFC 6582 4.1). NewReno's ssthresh = half the data in flight, with SACK the RFC 6675 pipe
                # (as ns-3); CUBIC uses cwnd (RFC 9438 4.6).
                self.fast_retransmits += 1
                cc.on_loss(self._sack_pipe() if self.use_sack else self.nxt - una)
                self.recover = self.high_tx - 1
                self.in_recovery = True
                if self.use_sack:
                    # RFC 6675 5 with PRR (RFC 6937): the first hole at once, then holes and new data as PRR allows.
                    self.episode += 1
                    self.retx_out.clear()
                    self.recover_fs = max(self.nxt - una, 1)
                    self.prr_delivered = 0
                    self.prr_out = 1
                    self.retx_episode[una] = self.episode
                    self.retx_out.append(una)
                    self._send(engine, una, t)
                    self.hole = una + 1
                    self._prr_step(engine, t, newly_sacked)
                else:
                    self._send(engine, una, t)
                    cc.cwnd = cc.ssthresh + 3.0

    def _on_timeout(self, engine: Engine, t: float) -> None:
        """Retransmission timeout (RFC 6298 5.4-5.7): back off, cwnd = 1, go back to the first hole."""
        self.timeouts += 1
        self.cc.on_timeout(self.nxt - self.una)
        self.rto = min(self.rto * 2.0, self.max_rto)
        self.in_recovery = False
        self.dupacks = 0
        self.recover = self.high_tx - 1
        self.episode += 1
        self.retx_out.clear()
        self.nxt = self.una
        self._send(engine, self.nxt, t)
        self.nxt += 1
        self.rto_deadline = t + self.rto

    def _sack_pipe(self) -> int:
        """RFC 6675 SetPipe: unSACKed segments not deemed lost, plus those resent in this episode."""
        una = self.una
        retx_out = self.retx_out
        sacked = self.sacked
        while retx_out and retx_out[0] < una:
            retx_out.popleft()
        highest = self.highest_sacked
        lost_top = highest - 3  # IsLost: DupThresh SACKed segments above (RFC 6675 4)
        lost = 0
        if lost_top >= una:
            sacked_below = self.sacked_count
            for s in range(max(lost_top + 1, una), highest + 1):
                sacked_below -= sacked[s]
            lost = lost_top - una + 1 - sacked_below
        resent = 0
        for s in retx_out:
            if not sacked[s]:
                resent += 1
        pipe = self.nxt - una - self.sacked_count - lost + resent
        return pipe if pipe > 0 else 0

    def _sack_send(self, engine: Engine, now: float, pipe: int) -> int:
        """RFC 6675 5 (NextSeg): fill lost holes first, then new data, while pipe < cwnd; return the count."""
        sent = 0
        cc = self.cc
        window = cc.cwnd if cc.cwnd < self.rwnd else self.rwnd
        sacked = self.sacked
        retx_episode = self.retx_episode
        episode = self.episode
        if self.hole < self.una:
            self.hole = self.una
        while pipe + 1 <= window:
            hole = self.hole
            highest = self.highest_sacked
            while hole + 3 <= highest and (sacked[hole] or retx_episode[hole] == episode):
                hole += 1
            self.hole = hole
            if hole + 3 <= highest and hole < self.nxt:
                retx_episode[hole] = episode
                self.retx_out.append(hole)
                self._send(engine, hole, now)
                self.hole = hole + 1
            elif self.nxt < self.n and self.nxt - self.una < self.rwnd:
                self._send(engine, self.nxt, now)
                self.nxt += 1
            else:
                break
            pipe += 1
            sent += 1
        return sent

    def _prr_step(self, engine: Engine, now: float, delivered: int) -> None:
        """Proportional Rate Reduction (RFC 6937 with the slow-start reduction bound)."""
        self.prr_delivered += delivered
        pipe = self._sack_pipe()
        ssthresh = self.cc.ssthresh
        if pipe > ssthresh:
            sndcnt = math.ceil(self.prr_delivered * ssthresh / self.recover_fs) - self.prr_out
        else:
            limit = max(self.prr_delivered - self.prr_out, delivered) + 1
            sndcnt = min(int(ssthresh) - pipe, limit)
        if sndcnt < 0:
            sndcnt = 0
        self.cc.cwnd = float(pipe + sndcnt)
        self.prr_out += self._sack_send(engine, now, pipe)

    # -- the receiver --------------------------------------------------------------------------------------------
    def deliver(self, engine: Engine, payload, arrival: float | None, decided_s: float) -> None:
        period, i = payload
        if period != self.period or not self.active:
            return  # a packet of a busy period given up at the time cap
        if i < 0:
            self._syn_fate(arrival, decided_s)
            return
        if arrival is None:
            return
        received = self.received
        rcv_nxt = self.rcv_nxt
        in_order = i == rcv_nxt
        if not received[i]:
            received[i] = 1
            if in_order:
                n = self.n
                rcv_nxt += 1
                while rcv_nxt < n and received[rcv_nxt]:
                    rcv_nxt += 1
                self.rcv_nxt = rcv_nxt
                self.advances.append(rcv_nxt)
                self.advance_times.append(arrival)
                pmsg_end = self.pmsg_end
                while self.next_done < len(pmsg_end) and pmsg_end[self.next_done] <= rcv_nxt:
                    state = self.pmsgs[self.next_done]
                    state.done_s = arrival
                    heapq.heappush(engine.heap, (arrival, FINAL, 0, self.fid, state.index, None))
                    self.next_done += 1
        ackq = self.ackq
        ack_delay = self.ack_delay
        if self.delack and in_order and i + 1 == rcv_nxt:
            # In-order data: ACK every second segment, or when the delayed-ACK timer fires (RFC 1122 4.2.3.2).
            if self.pending_ack_s < INF:
                if arrival <= self.pending_ack_s + self.delack_timeout:
                    self.pending_ack_s = INF
                    ackq.append((arrival + ack_delay, rcv_nxt, i))
                    return
                ackq.append((self.pending_ack_s + self.delack_timeout + ack_delay, self.pending_cum,
                             self.pending_seg))
            self.pending_ack_s = arrival
            self.pending_cum = rcv_nxt
            self.pending_seg = i
            return
        if self.pending_ack_s < INF:
            ackq.append((min(self.pending_ack_s + self.delack_timeout, arrival) + ack_delay, self.pending_cum,
                         self.pending_seg))
            self.pending_ack_s = INF
        ackq.append((arrival + ack_delay, rcv_nxt, i))

    # -- results -------------------------------------------------------------------------------------------------
    def on_final(self, engine: Engine, t: float, index: int) -> None:
        state = self.states.get(index)
        if state is None:
            return
        if state.done_s <= t or t >= state.deadline_abs_s:
            del self.states[index]
            self._finish_tcp(engine, state, cut=False)

    def _in_order_segments_by(self, when_s: float) -> int:
        """rcv_nxt at time ``when_s`` (arrivals are processed in order, so the times are sorted)."""
        k = bisect_right(self.advance_times, when_s)
        return self.advances[k - 1] if k else 0

    def _finish_tcp(self, engine: Engine, state: _TcpMessage, cut: bool) -> None:
        """The single-path engine's end-of-run bookkeeping for one message."""
        message = state.message
        size = message.size_bytes
        mss = self.mss
        deadline_abs_s = state.deadline_abs_s
        if state.done_s <= deadline_abs_s and state.done_s < INF:
            _finish(engine, message, arrival_s=state.done_s, delivered=size, lost=[],
                    retransmissions=state.retransmissions)
            return
        if deadline_abs_s < INF:
            # Late data counts as lost: what was in order by the deadline is delivered.
            in_order = self._in_order_segments_by(deadline_abs_s)
        else:
            in_order = self.rcv_nxt if cut else 0
        segments = max(0, min(in_order, state.end) - state.start)
        delivered = min(size, segments * mss)
        _finish(engine, message, arrival_s=INF, delivered=delivered, lost=[(delivered, size)],
                retransmissions=state.retransmissions)


def _finish(engine: Engine, message: Message, arrival_s: float, delivered: int, lost: list,
            retransmissions: int, settled_s: float | None = None) -> None:
    """Write a message's final results."""
    complete = not lost
    message.arrival_s = arrival_s if complete else INF
    message.delivered_bytes = delivered
    message.lost_ranges = lost
    message.retransmissions = retransmissions
    message.complete = complete
    if settled_s is None:
        settled_s = message.arrival_s if complete else (
            message.at_s + message.deadline_s if message.deadline_s is not None else INF)
    message.settled_s = settled_s
    engine.finalize(message)


# ---------------------------------------------------------------------------------------------------------------
# UDP


class _UdpMessage:
    """A message on a UDP flow: its datagrams, their fates, and the pass (first pass or NACK round) in progress."""

    def __init__(self, message: Message, index: int, payload: int, config: UdpConfig):
        self.message = message
        self.index = index
        size = message.size_bytes
        count = -(-size // payload)
        self.sizes = [payload] * (count - 1) + [size - payload * (count - 1)]
        k, r = config.fec_k, config.fec_r
        # First pass: the data, with r parity datagrams (full size) after every k data datagrams.
        self.layout: list[tuple[int, int]] = []
        wire = []
        parity = 0
        for i, s in enumerate(self.sizes):
            self.layout.append((i, i // k if r else 0))
            wire.append(s)
            if r and ((i + 1) % k == 0 or i == count - 1):
                for _ in range(r):
                    self.layout.append((-1, i // k))
                    wire.append(payload)
                    parity += 1
        self.parity = parity
        self.data_arrival = [INF] * count
        self.pass_payloads = wire          # payload bytes of each datagram of the current pass
        self.pass_items: list[int] = []    # data index of each datagram of a NACK round
        self.pass_number = 0
        self.pass_arrival = [INF] * len(wire)
        self.outstanding = len(wire)
        self.pass_last_send_s = message.at_s
        self.decided_s = message.at_s      # when the last fate so far was decided (arrival or drop)
        self.rounds = 0
        self.retransmissions = 0
        self.recovered = 0
        self.result = None

    def copy(self) -> "_UdpMessage":
        other = object.__new__(_UdpMessage)
        other.__dict__.update(self.__dict__)
        other.data_arrival = list(self.data_arrival)
        other.pass_arrival = list(self.pass_arrival)
        return other


class UdpFlow(_Flow):
    """A UDP sender, as :class:`netsim.udp.UdpSender` but sending each datagram at its own time.

    Datagrams leave one after another, paced (at the path's slowest link by default, or ``pacing``), or in one
    burst; a NACK round's resends go before new data. Counters: ``datagrams_sent``, ``parity_sent``,
    ``retransmissions``, ``datagrams_recovered``.
    """

    def __init__(self, fid: int, path: Path, config: UdpConfig, max_sim_time_s: float):
        super().__init__(fid, path, max_sim_time_s)
        self.config = config
        self.payload = path.mtu_bytes - UDP_HEADER_BYTES
        if config.burst:
            self.gap_per_byte = 0.0
        elif config.pacing_mbps:
            self.gap_per_byte = 8.0 / (config.pacing_mbps * 1e6)
        else:
            self.gap_per_byte = 1.0 / path.rate_bytes_per_s  # the slowest link's rate: no queue of its own
        self.queue: deque = deque()   # (message number, datagram) of first passes, in order
        self.resend: list = []        # heap of (earliest send time, order, message number, datagram)
        self.resend_order = 0
        self.next_free_s = -INF
        self.datagrams_sent = 0
        self.parity_sent = 0
        self.retransmissions = 0
        self.datagrams_recovered = 0

    def clone(self) -> "UdpFlow":
        """An independent copy (the engine's copy-on-write)."""
        other = object.__new__(UdpFlow)
        other.__dict__.update(self.__dict__)
        other.states = {index: state.copy() for index, state in self.states.items()}
        other.queue = self.queue.copy()
        other.resend = self.resend[:]
        return other

    def next_event_s(self) -> float:
        if self.queue:
            ready = self.states[self.queue[0][0]].message.at_s
        else:
            ready = INF
        if self.resend and self.resend[0][0] < ready:
            ready = self.resend[0][0]
        return ready if ready >= self.next_free_s else self.next_free_s

    def on_message(self, engine: Engine, t: float, index: int, message: Message) -> None:
        if not self.path.hop_ids:
            _finish(engine, message, arrival_s=t, delivered=message.size_bytes, lost=[], retransmissions=0)
            return
        state = _UdpMessage(message, index, self.payload, self.config)
        self.states[index] = state
        self.parity_sent += state.parity
        self.queue.extend((index, j) for j in range(len(state.pass_payloads)))

    def on_wake(self, engine: Engine, t: float) -> None:
        while True:
            if t < self.next_free_s:
                return
            if self.resend and self.resend[0][0] <= t:
                _, _, index, j = heapq.heappop(self.resend)
            elif self.queue:
                index, j = self.queue.popleft()
            else:
                return
            state = self.states[index]
            wire = state.pass_payloads[j] + UDP_HEADER_BYTES
            self.datagrams_sent += 1
            state.pass_last_send_s = t
            self.next_free_s = t + wire * self.gap_per_byte
            engine.transmit(self, t, wire, (index, state.pass_number, j), False)

    def deliver(self, engine: Engine, payload, arrival: float | None, decided_s: float) -> None:
        index, pass_number, j = payload
        state = self.states.get(index)
        if state is None or pass_number != state.pass_number:
            return
        state.pass_arrival[j] = INF if arrival is None else arrival
        when = decided_s if arrival is None else arrival
        if when > state.decided_s:
            state.decided_s = when
        state.outstanding -= 1
        if state.outstanding == 0:
            self._end_pass(engine, state)

    def _end_pass(self, engine: Engine, state: _UdpMessage) -> None:
        """Every datagram of the pass has arrived or been lost: FEC, then a NACK round or the results
        (netsim.udp.UdpSender.put, the same rules)."""
        config = self.config
        message = state.message
        arrivals = state.pass_arrival
        data_arrival = state.data_arrival
        if state.pass_number == 0:
            k, r = config.fec_k, config.fec_r
            count = len(data_arrival)
            block_arrivals: dict[int, list[float]] = {}
            block_data_lost: dict[int, list[int]] = {}
            for (index, block), arrival in zip(state.layout, arrivals):
                if r:
                    block_arrivals.setdefault(block, []).append(arrival)
                if index >= 0:
                    data_arrival[index] = arrival
                    if arrival == INF and r:
                        block_data_lost.setdefault(block, []).append(index)
            if r:
                for block, lost in block_data_lost.items():
                    received = sorted(a for a in block_arrivals[block] if a < INF)
                    block_size = min(k, count - block * k)
                    if len(received) >= block_size:
                        # An MDS code: decodable once any block_size of the block's datagrams are in.
                        recovered_s = received[block_size - 1]
                        for index in lost:
                            data_arrival[index] = recovered_s
                            self.datagrams_recovered += 1
        else:
            for i, arrival in zip(state.pass_items, arrivals):
                data_arrival[i] = arrival
        missing = [i for i, a in enumerate(data_arrival) if a == INF]
        deadline_abs_s = message.at_s + message.deadline_s if message.deadline_s is not None else INF
        if missing and state.rounds < config.nack_rounds:
            # The receiver reports the holes when it expects the pass to be over; the report takes the reverse
            # delay. It cannot act before it knows the fates, hence the max with now.
            received_times = [a for a in arrivals if a < INF]
            path = self.path
            expected_end_s = max(max(received_times, default=0.0),
                                 state.pass_last_send_s + path.delay_s
                                 + path.serialisation_s(self.payload + UDP_HEADER_BYTES))
            resend_s = max(expected_end_s + path.reverse_delay_s, engine.now)
            # No round that cannot finish within the time cap, nor one that starts after the deadline (its data
            # would count as lost anyway).
            if resend_s - message.at_s <= self.max_sim_time_s and resend_s < deadline_abs_s:
                state.rounds += 1
                state.pass_number += 1
                state.pass_items = missing
                state.pass_payloads = [state.sizes[i] for i in missing]
                state.pass_arrival = [INF] * len(missing)
                state.outstanding = len(missing)
                state.retransmissions += len(missing)
                self.retransmissions += len(missing)
                for j in range(len(missing)):
                    self.resend_order += 1
                    heapq.heappush(self.resend, (resend_s, self.resend_order, state.index, j))
                return
        lost_ranges: list[tuple[int, int]] = []
        delivered = 0
        last_arrival = message.at_s
        payload = self.payload
        for i, arrival in enumerate(data_arrival):
            begin = i * payload
            end = begin + state.sizes[i]
            if arrival <= deadline_abs_s and arrival < INF:
                delivered += state.sizes[i]
                if arrival > last_arrival:
                    last_arrival = arrival
            elif lost_ranges and lost_ranges[-1][1] == begin:
                lost_ranges[-1] = (lost_ranges[-1][0], end)
            else:
                lost_ranges.append((begin, end))
        if lost_ranges:
            # The receiver holds all it will get once every fate is decided (or at the deadline).
            received = max([a for a in data_arrival if a < INF], default=message.at_s)
            settled_s = min(deadline_abs_s, max(received, state.decided_s))
        else:
            settled_s = last_arrival
        state.result = (last_arrival, delivered, lost_ranges, settled_s)
        heapq.heappush(engine.heap, (max(settled_s, engine.now), FINAL, 0, self.fid, state.index, None))

    def on_final(self, engine: Engine, t: float, index: int) -> None:
        state = self.states.pop(index, None)
        if state is None:
            return
        last_arrival, delivered, lost_ranges, settled_s = state.result
        _finish(engine, state.message, arrival_s=last_arrival, delivered=delivered, lost=lost_ranges,
                retransmissions=state.retransmissions, settled_s=settled_s)
