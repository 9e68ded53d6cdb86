"""A persistent TCP connection (one sending direction) at segment granularity.

What is modelled, and from where:
- handshake once per session (SYN / SYN-ACK round trip, optionally charged to the first message); its round trip
  seeds the RTT estimator, as Linux and ns-3 do;
- slow start from IW = 10 segments (RFC 6928), congestion avoidance as NewReno (RFC 5681 3.1, RFC 6582) or
  CUBIC (RFC 9438: C = 0.4, beta = 0.7, fast convergence, TCP-friendly region; no HyStart);
- fast retransmit on the third duplicate ACK, limited transmit (RFC 3042); with SACK (default) a per-segment
  scoreboard (RFC 6675) and Proportional Rate Reduction (RFC 6937); without it NewReno fast recovery with window
  inflation, partial-ACK retransmission and full-ACK deflation (RFC 6582 3.2);
- retransmission timer per RFC 6298 (SRTT/RTTVAR, Karn's rule, exponential back-off) with Linux's 200 ms floor;
  on a timeout cwnd = 1 segment and the sender goes back to the first unacknowledged segment;
- slow-start restart: after an idle period longer than one RTO, cwnd = min(cwnd, IW) (RFC 5681 4.1);
- optional delayed ACKs (every second full segment or after a timeout, immediate ACK for out-of-order data);
- a receive window capping the bytes in flight.

A message is delivered when its last byte is in order at the receiver (head-of-line blocking): the receiver keeps
the out-of-order segments and its cumulative ACK jumps when a hole is filled.

The sender is a small event loop with two event sources, ACK arrivals and the retransmission timer. ACKs arrive in
the order their segments were sent (a FIFO link, no reordering), so the ACK queue is a plain deque and no heap is
needed; each segment costs a handful of float operations (docs/netsim.md, "Granularity").

Example::

    env = Environment(seed=0)
    down = Link(env, LinkConfig(bandwidth_mbps=50, delay_ms=17), "down")
    tcp = TcpConnection(env, down, reverse_delay_s=0.017, config=TcpConfig())
    tcp.put(Message(size_bytes=300_000, at_s=0.0))
    print(tcp.out[0].arrival_s)
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from dataclasses import dataclass, field

from netsim.config import TCP_HEADER_BYTES, TcpConfig
from netsim.env import Environment
from netsim.link import Link

CUBIC_C = 0.4     # RFC 9438 4.1
CUBIC_BETA = 0.7  # RFC 9438 4.6
ACK_BYTES = TCP_HEADER_BYTES
# A message joining a busy period replays it from its start; beyond this many messages in one period (a sender
# that offers more than the path carries), later ones queue after the period instead, which keeps the cost of a
# send bounded.
MAX_REPLAYED_MESSAGES = 8


def rto_update(srtt_s, rttvar_s, rtt_s: float, min_rto_s: float, max_rto_s: float) -> tuple:
    """RFC 6298 2.2-2.3 (alpha = 1/8, beta = 1/4, K = 4, G = 1 ms clock granularity), clamped to
    [min_rto, max_rto] (2.4-2.5): (srtt, rttvar, rto) after one RTT sample; ``srtt_s`` None before the first."""
    if srtt_s is None:
        srtt_s, rttvar_s = rtt_s, rtt_s / 2.0
    else:
        rttvar_s = 0.75 * rttvar_s + 0.25 * abs(srtt_s - rtt_s)
        srtt_s = 0.875 * srtt_s + 0.125 * rtt_s
    rto = srtt_s + max(0.001, 4.0 * rttvar_s)
    return srtt_s, rttvar_s, min(max(rto, min_rto_s), max_rto_s)


@dataclass(eq=False)  # identity semantics: two equal-looking messages are still two messages
class Message:
    size_bytes: int
    at_s: float
    deadline_s: float | None = None
    # results
    arrival_s: float = math.inf
    delivered_bytes: int = 0
    retransmissions: int = 0
    complete: bool = False
    lost_ranges: list = field(default_factory=list)
    # When the receiver holds all it will ever get of this message (= arrival_s when complete).
    settled_s: float = math.inf


class _CongestionState:
    """cwnd bookkeeping in segments (floats), shared by NewReno and CUBIC."""

    def __init__(self, config: TcpConfig):
        self.cubic = config.congestion_control == "cubic"
        self.iw = float(config.initial_window_segments)
        self.cwnd = self.iw
        self.ssthresh = math.inf
        # CUBIC state (RFC 9438 4)
        self.w_max = 0.0
        self.epoch_start_s = None
        self.k_s = 0.0
        self.origin = 0.0
        self.w_est = 0.0

    def copy(self) -> "_CongestionState":
        other = object.__new__(_CongestionState)
        other.__dict__.update(self.__dict__)
        return other

    def on_ack(self, acked: int, now_s: float, min_rtt_s: float) -> None:
        cwnd = self.cwnd
        if cwnd < self.ssthresh:
            # Slow start: one segment per segment acknowledged (RFC 5681 3.1), stopping at ssthresh.
            room = self.ssthresh - cwnd
            grow = acked if acked <= room else room
            self.cwnd = cwnd + grow
            acked -= grow
            if acked <= 0:
                return
            cwnd = self.cwnd
        if not self.cubic:
            # NewReno congestion avoidance: +1 segment per window of ACKed data.
            self.cwnd = cwnd + acked / cwnd
            return
        if self.epoch_start_s is None:
            self.epoch_start_s = now_s
            if cwnd < self.w_max:
                self.k_s = ((self.w_max - cwnd) / CUBIC_C) ** (1.0 / 3.0)
                self.origin = self.w_max
            else:
                self.k_s = 0.0
                self.origin = cwnd
            self.w_est = cwnd
        # W_cubic(t + RTT) as the target (RFC 9438 4.2), RTT = the minimum seen.
        t = now_s - self.epoch_start_s + min_rtt_s
        target = self.origin + CUBIC_C * (t - self.k_s) ** 3
        if target > cwnd:
            increase = acked * (target - cwnd) / cwnd
        else:
            increase = acked * 0.01 / cwnd
        # TCP-friendly (Reno-emulation) region, RFC 9438 4.3.
        self.w_est += acked * (3.0 * (1.0 - CUBIC_BETA) / (1.0 + CUBIC_BETA)) / cwnd
        if self.w_est > cwnd + increase:
            increase = self.w_est - cwnd if self.w_est - cwnd < acked else acked
        self.cwnd = cwnd + increase

    def on_loss(self, flight_segments: int) -> None:
        """Multiplicative decrease on fast retransmit; sets ssthresh (cwnd is set by the caller)."""
        if self.cubic:
            cwnd = self.cwnd
            # Fast convergence (RFC 9438 4.7).
            self.w_max = cwnd * (1.0 + CUBIC_BETA) / 2.0 if cwnd < self.w_max else cwnd
            self.ssthresh = max(cwnd * CUBIC_BETA, 2.0)
            self.epoch_start_s = None
        else:
            self.ssthresh = max(flight_segments / 2.0, 2.0)  # RFC 5681 eq. (4)

    def on_timeout(self, flight_segments: int) -> None:
        self.on_loss(flight_segments)
        self.cwnd = 1.0


class TcpConnection:
    """One direction of a persistent TCP connection over ``link``; ACKs return after ``reverse_delay_s``.

    ``put(message)`` appends a message to the byte stream at ``message.at_s`` and fills in its results; finished
    messages are appended to ``.out``. Counters: ``segments_sent``, ``retransmissions``, ``timeouts``,
    ``fast_retransmits``, ``messages_delivered``.
    """

    def __init__(self, env: Environment, link: Link, reverse_delay_s: float, config: TcpConfig,
                 reverse_rate_bytes_per_s: float = math.inf, max_sim_time_s: float = 600.0):
        self.env = env
        self.link = link
        self.config = config
        self.mss_bytes = link.config.mtu_bytes - TCP_HEADER_BYTES
        self.ack_delay_s = reverse_delay_s + ACK_BYTES / reverse_rate_bytes_per_s
        self.max_sim_time_s = max_sim_time_s
        self.out: list[Message] = []
        self.established = False
        self.cc = _CongestionState(config)
        self.srtt_s: float | None = None
        self.rttvar_s = 0.0
        self.rto_s = config.initial_rto_ms * 1e-3
        self.min_rtt_s = math.inf
        self.last_activity_s = -math.inf  # last send or ACK; slow-start restart measures idle from here
        self.segments_sent = 0
        self.retransmissions = 0
        self.timeouts = 0
        self.fast_retransmits = 0
        # The current busy period: messages that overlap in time are simulated together (see put()).
        self._period_messages: list[Message] = []
        self._period_state = None
        self._period_end_s = -math.inf
        # Transmissions to lose on purpose, as (segment number in the busy period, attempt number from 0): used to
        # replay another simulator's loss pattern when investigating a difference.
        self.scripted_drops: set[tuple[int, int]] = set()

    # ---------------------------------------------------------------------------------------------------------
    def put(self, message: Message) -> Message:
        at_s = message.at_s
        joins = (self._period_messages and at_s < self._period_end_s and self.link.last_user is self
                 and len(self._period_messages) < MAX_REPLAYED_MESSAGES)
        if joins:
            # A message sent while earlier ones are still in flight shares their busy period: replay the period
            # from its start with all its messages (same random streams), so the new bytes queue behind the old
            # ones on the same connection and their ACKs can trigger the old ones' loss recovery.
            self._restore(self._period_state)
            self._period_messages.append(message)
        else:
            if self._period_messages and at_s < self._period_end_s:
                # Another flow used the link since, or the backlog is already MAX_REPLAYED_MESSAGES deep: the new
                # message waits for the connection to drain.
                message_start_s = self._period_end_s
            else:
                message_start_s = at_s
            self._period_messages = [message]
            self._period_state = self._snapshot()
            self._period_start_s = message_start_s
        self._period_end_s = self._run(self._period_messages, self._period_start_s)
        self.out.append(message)
        return message

    @property
    def messages_delivered(self) -> int:
        return sum(1 for message in self.out if message.complete)

    def _snapshot(self):
        return (self.established, self.cc.copy(), self.srtt_s, self.rttvar_s, self.rto_s, self.min_rtt_s,
                self.last_activity_s, self.segments_sent, self.retransmissions, self.timeouts,
                self.fast_retransmits, self.link.snapshot())

    def _restore(self, state) -> None:
        (self.established, cc, self.srtt_s, self.rttvar_s, self.rto_s, self.min_rtt_s, self.last_activity_s,
         self.segments_sent, self.retransmissions, self.timeouts, self.fast_retransmits, link_state) = state
        self.cc = cc.copy()
        self.link.restore(link_state)

    # ---------------------------------------------------------------------------------------------------------
    def _run(self, messages: list[Message], start_s: float) -> float:
        """Simulate the busy period; fill in every message's results; return when the last ACK arrived."""
        config = self.config
        link = self.link
        transmit = link.transmit
        mss = self.mss_bytes
        ack_delay = self.ack_delay_s
        cc = self.cc
        rwnd_segments = max(1, int(config.receive_window_bytes // mss))
        min_rto = config.min_rto_ms * 1e-3
        max_rto = config.max_rto_ms * 1e-3

        # Segment the stream; each message starts a new segment (TCP_NODELAY, no Nagle).
        seg_bytes: list[int] = []
        seg_avail_s: list[float] = []
        seg_message: list[int] = []
        message_end_seg: list[int] = []
        for index, message in enumerate(messages):
            full, rest = divmod(message.size_bytes, mss)
            count = full + (1 if rest else 0)
            seg_bytes.extend([mss] * full)
            if rest:
                seg_bytes.append(rest)
            avail = max(message.at_s, start_s)
            seg_avail_s.extend([avail] * count)
            seg_message.extend([index] * count)
            message_end_seg.append(len(seg_bytes))
            message.arrival_s = math.inf
            message.delivered_bytes = 0
            message.retransmissions = 0
            message.complete = False
            message.lost_ranges = []
        n = len(seg_bytes)
        done_s = [math.inf] * len(messages)

        t = max(start_s, messages[0].at_s)
        if not self.established:
            # SYN out, SYN-ACK back: the round trip also gives the first RTT sample (RFC 6298 2.2). When the
            # handshake is not charged, the connection was set up before the session and nothing is sent.
            if config.count_handshake:
                syn_timeout_s = config.initial_rto_ms * 1e-3
                while True:
                    syn_arrival = transmit(t, TCP_HEADER_BYTES, self)
                    if syn_arrival is not None or t - start_s > self.max_sim_time_s:
                        break
                    t += syn_timeout_s  # a lost SYN is resent after the initial RTO, doubling (RFC 6298 5.7)
                    syn_timeout_s *= 2.0
                handshake_rtt = (syn_arrival - t if syn_arrival is not None else link.delay_s) + ack_delay
                t += handshake_rtt
            else:
                handshake_rtt = link.delay_s + TCP_HEADER_BYTES / link.rate_bytes_per_s + ack_delay
            self._rtt_sample(handshake_rtt, min_rto, max_rto)
            self.established = True
        elif config.slow_start_restart and t - self.last_activity_s > self.rto_s:
            cc.cwnd = min(cc.cwnd, cc.iw)  # RFC 5681 4.1 restart window
        cap_s = t + self.max_sim_time_s

        srtt = self.srtt_s
        rttvar = self.rttvar_s
        send_time = [0.0] * n
        retransmitted = bytearray(n)
        received = bytearray(n)
        # ACKs in flight back to the sender, in arrival order:
        # (arrival time, cumulative ACK = next segment expected, segment that triggered it = its SACK block).
        ackq: deque = deque()
        una = 0
        nxt = 0
        high_tx = 0
        rcv_nxt = 0
        next_done = 0  # next message whose completion the receiver has not seen
        dupacks = 0
        in_recovery = False
        recover = -1
        rto_deadline = math.inf
        delack = config.delayed_ack
        delack_timeout = config.delayed_ack_timeout_ms * 1e-3
        pending_ack_s = math.inf  # delayed ACK held by the receiver (arrival time of the unacked segment)
        pending_cum = 0
        pending_seg = 0
        segments_sent = 0
        retransmissions = 0
        seg_retx_count = [0] * len(messages)
        last_ack_s = t
        advances: list = []  # (time, rcv_nxt) each time in-order data reached the receiver
        # SACK scoreboard (RFC 2018 / RFC 6675), as the sender knows it from the ACKs that have arrived.
        use_sack = config.sack
        sacked = bytearray(n)
        sacked_count = 0      # SACKed segments at or above una
        highest_sacked = -1
        episode = 0           # loss-recovery episode number; retx_episode[s] == episode: resent in this one
        retx_episode = [0] * n
        retx_out: deque = deque()  # segments resent in this episode (NextSeg rule 1), oldest first
        hole = 0              # scan pointer for the next lost segment
        prr_delivered = 0     # RFC 6937 state
        prr_out = 0
        recover_fs = 1

        scripted = self.scripted_drops
        attempts = [0] * n if scripted else None

        def send(i: int, now: float) -> None:
            nonlocal high_tx, rcv_nxt, next_done, segments_sent, retransmissions, pending_ack_s, pending_cum
            nonlocal pending_seg
            segments_sent += 1
            send_time[i] = now
            if i < high_tx:
                retransmissions += 1
                retransmitted[i] = 1
                seg_retx_count[seg_message[i]] += 1
            else:
                high_tx = i + 1
            if scripted:
                attempt = attempts[i]
                attempts[i] = attempt + 1
                if (i, attempt) in scripted:
                    link.scripted_losses.add(link.packets_offered)
            arrival = transmit(now, seg_bytes[i] + TCP_HEADER_BYTES, self, True)
            if arrival is None:
                return
            in_order = i == rcv_nxt
            if not received[i]:
                received[i] = 1
                if in_order:
                    rcv_nxt += 1
                    while rcv_nxt < n and received[rcv_nxt]:
                        rcv_nxt += 1
                    advances.append((arrival, rcv_nxt))
                    while next_done < len(messages) and message_end_seg[next_done] <= rcv_nxt:
                        done_s[next_done] = arrival
                        next_done += 1
            if delack and in_order and i + 1 == rcv_nxt:
                # In-order data: ACK every second segment, or when the delayed-ACK timer fires.
                if pending_ack_s < math.inf:
                    if arrival <= pending_ack_s + delack_timeout:
                        pending_ack_s = math.inf
                        ackq.append((arrival + ack_delay, rcv_nxt, i))
                        return
                    ackq.append((pending_ack_s + delack_timeout + ack_delay, pending_cum, pending_seg))
                pending_ack_s = arrival
                pending_cum = rcv_nxt
                pending_seg = i
                return
            if pending_ack_s < math.inf:
                ackq.append((min(pending_ack_s + delack_timeout, arrival) + ack_delay, pending_cum, pending_seg))
                pending_ack_s = math.inf
            ackq.append((arrival + ack_delay, rcv_nxt, i))

        def sack_pipe() -> int:
            """RFC 6675 SetPipe: unSACKed segments not deemed lost, plus those resent in this episode."""
            while retx_out and retx_out[0] < una:
                retx_out.popleft()
            lost_top = highest_sacked - 3  # IsLost: DupThresh SACKed segments above (RFC 6675 4)
            lost = 0
            if lost_top >= una:
                sacked_below = sacked_count
                for s in range(max(lost_top + 1, una), highest_sacked + 1):
                    sacked_below -= sacked[s]
                lost = lost_top - una + 1 - sacked_below
            resent = 0
            for s in retx_out:
                if not sacked[s]:
                    resent += 1
            pipe = nxt - una - sacked_count - lost + resent
            return pipe if pipe > 0 else 0

        def sack_send(now: float, pipe: int) -> int:
            """RFC 6675 5 (NextSeg): fill lost holes first, then new data, while pipe < cwnd; return the count."""
            nonlocal hole, nxt
            sent = 0
            window = cc.cwnd if cc.cwnd < rwnd_segments else rwnd_segments
            if hole < una:
                hole = una
            while pipe + 1 <= window:
                while hole + 3 <= highest_sacked and (sacked[hole] or retx_episode[hole] == episode):
                    hole += 1
                if hole + 3 <= highest_sacked and hole < nxt:
                    retx_episode[hole] = episode
                    retx_out.append(hole)
                    send(hole, now)
                    hole += 1
                elif nxt < n and seg_avail_s[nxt] <= now and nxt - una < rwnd_segments:
                    send(nxt, now)
                    nxt += 1
                else:
                    break
                pipe += 1
                sent += 1
            return sent

        def prr_step(now: float, delivered: int) -> None:
            """Proportional Rate Reduction (RFC 6937, with the slow-start reduction bound; Linux's and ns-3's
            default): during recovery, send about ssthresh/RecoverFS segments per segment delivered."""
            nonlocal prr_delivered, prr_out
            prr_delivered += delivered
            pipe = sack_pipe()
            ssthresh = cc.ssthresh
            if pipe > ssthresh:
                sndcnt = math.ceil(prr_delivered * ssthresh / recover_fs) - prr_out
            else:
                limit = max(prr_delivered - prr_out, delivered) + 1
                sndcnt = min(int(ssthresh) - pipe, limit)
            if sndcnt < 0:
                sndcnt = 0
            cc.cwnd = float(pipe + sndcnt)
            prr_out += sack_send(now, pipe)

        # Vectorised runs (docs/netsim.md, "Granularity"): while nothing is lost and the receiver has every
        # segment sent, the ACKs already on their way are processed as one batch and the segments they release go
        # through the link with numpy. A batch only holds ACKs that arrive before the first ACK any new segment
        # could cause (one minimum round trip after the first), so the order of events is exactly the scalar one.
        vector_ok = link.vector_ok and not delack and n >= 64 and not scripted
        min_round_trip_s = link.delay_s + ack_delay + (TCP_HEADER_BYTES + 1) / link.rate_bytes_per_s
        all_available_s = seg_avail_s[-1] if n else 0.0
        seg_wire = None
        scalar_until_seg = 0  # after a vectorised run met a drop, segments before this go one by one

        def run_batch(limit: int) -> int:
            """Process up to ``limit`` queued ACKs in one vectorised step; return how many were processed."""
            nonlocal una, nxt, high_tx, rcv_nxt, next_done, t, last_ack_s, srtt, rttvar, rto_deadline
            nonlocal segments_sent, seg_wire, cc, scalar_until_seg
            horizon_s = ackq[0][0] + min_round_trip_s
            if horizon_s > cap_s:
                horizon_s = cap_s
            batch = []
            last_cum = una
            for entry in ackq:
                # Only ACKs that acknowledge new data: a duplicate ACK (the receiver got a segment twice) counts
                # towards fast retransmit and may release a limited-transmit segment, which the scalar path does.
                if (entry[0] >= horizon_s or entry[1] != entry[2] + 1 or entry[1] <= last_cum
                        or len(batch) >= limit):
                    break
                last_cum = entry[1]
                batch.append(entry)
            if len(batch) < 4:
                return 0
            saved_cc = cc.copy()
            b_srtt, b_rttvar, b_min_rtt, b_rto = srtt, rttvar, self.min_rtt_s, self.rto_s
            sampled = False
            released = []
            u = una
            high = nxt
            cwnd = cc.cwnd
            ssthresh = cc.ssthresh
            # Slow start and NewReno growth inlined (the same arithmetic as _CongestionState.on_ack); CUBIC's
            # congestion avoidance calls on_ack.
            simple_ca = not cc.cubic
            for a_s, cum, _ in batch:
                if cum <= u:
                    released.append(0)
                    continue
                if not retransmitted[cum - 1]:
                    sampled = True
                    rtt = a_s - send_time[cum - 1]
                    if rtt < b_min_rtt:
                        b_min_rtt = rtt
                    delta = b_srtt - rtt
                    b_rttvar = 0.75 * b_rttvar + 0.25 * (delta if delta > 0 else -delta)
                    b_srtt = 0.875 * b_srtt + 0.125 * rtt
                acked = cum - u
                if cwnd + acked <= ssthresh:
                    cwnd += acked
                elif simple_ca and cwnd >= ssthresh:
                    cwnd += acked / cwnd
                else:
                    cc.cwnd = cwnd
                    cc.on_ack(acked, a_s, b_min_rtt)
                    cwnd = cc.cwnd
                u = cum
                allowed = u + int(cwnd if cwnd < rwnd_segments else rwnd_segments)
                if allowed > n:
                    allowed = n
                if allowed > high:
                    released.append(allowed - high)
                    high = allowed
                else:
                    released.append(0)
            cc.cwnd = cwnd
            if sampled:
                # A new sample: the RTO follows it (RFC 6298 2.3). Without one (Karn's rule: every ACKed segment
                # was a retransmission), a backed-off RTO stays as it is, as in the scalar path.
                b_rto = b_srtt + (4.0 * b_rttvar if b_rttvar > 0.00025 else 0.001)
                b_rto = min_rto if b_rto < min_rto else (max_rto if b_rto > max_rto else b_rto)
            total = high - nxt
            if total:
                if seg_wire is None:
                    seg_wire = np.asarray(seg_bytes, dtype=np.float64) + TCP_HEADER_BYTES
                send_s = np.repeat(np.fromiter((e[0] for e in batch), float, len(batch)), released)
                arrive_s, problem = link.transmit_many(send_s, seg_wire[nxt:high], self)
                if problem is not None:
                    # Keep only the ACKs whose segments all precede the packet that would be dropped; that packet
                    # and what follows it go through the scalar path.
                    cc = saved_cc
                    scalar_until_seg = nxt + problem + 1
                    keep = int(np.searchsorted(np.cumsum(released), problem, side="right"))
                    return run_batch(keep) if keep >= 4 else 0
                arrivals = arrive_s.tolist()
                send_times = send_s.tolist()
                send_time[nxt:high] = send_times
                received[nxt:high] = b"\x01" * total
                rcv_nxt = high
                advances.extend(zip(arrivals, range(nxt + 1, high + 1)))
                while next_done < len(messages) and message_end_seg[next_done] <= high:
                    done_s[next_done] = arrivals[message_end_seg[next_done] - 1 - nxt]
                    next_done += 1
                for _ in batch:
                    ackq.popleft()
                ackq.extend(zip((arrival + ack_delay for arrival in arrivals), range(nxt + 1, high + 1),
                                range(nxt, high)))
                segments_sent += total
                nxt = high
                high_tx = high
            else:
                for _ in batch:
                    ackq.popleft()
            srtt, rttvar, self.min_rtt_s, self.rto_s = b_srtt, b_rttvar, b_min_rtt, b_rto
            una = u
            t = last_ack_s = batch[-1][0]
            rto_deadline = t + self.rto_s if una < nxt else math.inf
            return len(batch)

        while una < n:
            if not in_recovery:
                # Send what the window allows (flight = nxt - una outside recovery). This comes before a vectorised
                # run: the segments the last ACK released leave at that ACK's time, not with the next batch.
                window = cc.cwnd if cc.cwnd < rwnd_segments else rwnd_segments
                while nxt < n and nxt - una + 1 <= window and seg_avail_s[nxt] <= t:
                    if sacked[nxt]:
                        nxt += 1  # after a timeout, skip what the receiver already reported
                        continue
                    send(nxt, t)
                    nxt += 1
            if (vector_ok and not in_recovery and not dupacks and not sacked_count and rcv_nxt == nxt == high_tx
                    and nxt >= scalar_until_seg and len(ackq) >= 4 and all_available_s <= ackq[0][0] and run_batch(len(ackq))):
                continue
            if nxt > una and rto_deadline == math.inf:
                rto_deadline = t + self.rto_s

            if ackq:
                next_ack_s, cum, ack_seg = ackq[0]
            elif pending_ack_s < math.inf:
                next_ack_s, cum, ack_seg = pending_ack_s + delack_timeout + ack_delay, pending_cum, pending_seg
            else:
                next_ack_s = math.inf
            # New data is an event of its own whenever the window has room for it: on an idle connection, and
            # also while earlier segments are in flight (a small message must not wait for the previous one's
            # ACK; the topology engine sends it on arrival too). In recovery, ACKs clock the sending.
            next_data_s = math.inf
            if nxt < n and seg_avail_s[nxt] > t and (nxt == una or (
                    not in_recovery and nxt - una + 1 <= (cc.cwnd if cc.cwnd < rwnd_segments else rwnd_segments))):
                next_data_s = seg_avail_s[nxt]
            timer_s = rto_deadline if una < nxt else math.inf
            event_s = next_ack_s if next_ack_s < timer_s else timer_s
            if next_data_s < event_s:
                event_s = next_data_s
            if event_s > cap_s or event_s == math.inf:
                break  # cannot finish within the simulated-time cap

            if next_ack_s <= timer_s and next_ack_s <= next_data_s:
                if ackq:
                    ackq.popleft()
                else:
                    pending_ack_s = math.inf
                t = next_ack_s
                last_ack_s = t
                newly_sacked = 0
                if use_sack and ack_seg >= cum and ack_seg >= una and not sacked[ack_seg]:
                    sacked[ack_seg] = 1
                    sacked_count += 1
                    newly_sacked = 1
                    if ack_seg > highest_sacked:
                        highest_sacked = ack_seg
                if cum > una:
                    acked = cum - una
                    if not retransmitted[cum - 1]:  # Karn's rule: no samples from retransmitted segments
                        # RFC 6298 2.3 (alpha = 1/8, beta = 1/4, K = 4, G = 1 ms), clamped by 2.4-2.5;
                        # inlined from _rtt_sample because it runs once per ACK.
                        rtt = t - send_time[cum - 1]
                        if rtt < self.min_rtt_s:
                            self.min_rtt_s = rtt
                        delta = srtt - rtt
                        rttvar = 0.75 * rttvar + 0.25 * (delta if delta > 0 else -delta)
                        srtt = 0.875 * srtt + 0.125 * rtt
                        rto = srtt + (4.0 * rttvar if rttvar > 0.00025 else 0.001)
                        rto = min_rto if rto < min_rto else (max_rto if rto > max_rto else rto)
                        self.rto_s = rto
                    if sacked_count:
                        for s in range(una, cum):
                            sacked_count -= sacked[s]
                    una = cum
                    if nxt < una:
                        nxt = una  # a go-back-N resend was overtaken by the receiver's buffered data
                    dupacks = 0
                    if in_recovery:
                        if una > recover:
                            # Full ACK: leave recovery at ssthresh (RFC 6582 3.2 step 3, RFC 6675 5).
                            cc.cwnd = cc.ssthresh
                            in_recovery = False
                        elif use_sack:
                            prr_step(t, acked + newly_sacked)
                        else:
                            # Partial ACK: resend the next hole, deflate by the amount acked, add one.
                            send(una, t)
                            cc.cwnd = max(cc.cwnd - acked + 1.0, 1.0)
                    else:
                        # Congestion window growth, limited to the window actually in use (RFC 7661 spirit:
                        # an application-limited sender does not grow cwnd).
                        cc.on_ack(acked, t, self.min_rtt_s)
                    rto_deadline = t + self.rto_s if una < nxt else math.inf  # RFC 6298 5.3
                elif nxt > una:
                    dupacks += 1
                    if in_recovery:
                        if use_sack:
                            prr_step(t, newly_sacked)
                        else:
                            cc.cwnd += 1.0  # window inflation, RFC 6582 3.2 step 4
                    elif dupacks < 3:
                        # Limited transmit (RFC 3042, on in Linux and ns-3): a new segment for each of the first
                        # two duplicate ACKs, so that small windows still reach three duplicates.
                        if (nxt < n and seg_avail_s[nxt] <= t and nxt - una < int(cc.cwnd) + dupacks
                                and nxt - una < rwnd_segments):
                            send(nxt, t)
                            nxt += 1
                    elif dupacks == 3 and una > recover:
                        # Fast retransmit (RFC 5681 3.2); "una > recover" avoids a second reduction for losses
                        # of the same window (RFC 6582 4.1).
                        self.fast_retransmits += 1
                        # NewReno's ssthresh = half the data in flight (RFC 5681 eq. (4)); with SACK, the data
                        # actually in the network (RFC 6675 pipe, as ns-3 computes it), not counting the segments
                        # already SACKed or deemed lost. CUBIC ignores it and uses cwnd (RFC 9438 4.6).
                        cc.on_loss(sack_pipe() if use_sack else nxt - una)
                        recover = high_tx - 1
                        in_recovery = True
                        if use_sack:
                            # RFC 6675 5 with PRR (RFC 6937): the first hole is resent at once, then holes and
                            # new data as PRR allows.
                            episode += 1
                            retx_out.clear()
                            recover_fs = max(nxt - una, 1)
                            prr_delivered = 0
                            prr_out = 1
                            retx_episode[una] = episode
                            retx_out.append(una)
                            send(una, t)
                            hole = una + 1
                            prr_step(t, newly_sacked)
                        else:
                            send(una, t)
                            cc.cwnd = cc.ssthresh + 3.0
            elif timer_s <= next_data_s:
                # Retransmission timeout (RFC 6298 5.4-5.7): back off, cwnd = 1, go back to the first hole.
                t = timer_s
                self.timeouts += 1
                cc.on_timeout(nxt - una)
                self.rto_s = min(self.rto_s * 2.0, max_rto)
                in_recovery = False
                dupacks = 0
                recover = high_tx - 1
                episode += 1
                retx_out.clear()
                nxt = una
                send(nxt, t)
                nxt += 1
                rto_deadline = t + self.rto_s
            else:
                # The next message is handed to the socket (slow-start restart only after a truly idle spell).
                idle_since = max(last_ack_s, send_time[nxt - 1] if nxt else t)
                if config.slow_start_restart and nxt == una and next_data_s - idle_since > self.rto_s:
                    cc.cwnd = min(cc.cwnd, cc.iw)
                t = next_data_s

        self.cc = cc  # a vectorised run that met a drop replaces the local state with its saved copy
        self.srtt_s = srtt
        self.rttvar_s = rttvar
        self.segments_sent += segments_sent
        self.retransmissions += retransmissions
        self.last_activity_s = last_ack_s
        for index, message in enumerate(messages):
            message.retransmissions = seg_retx_count[index]
            start_byte_seg = message_end_seg[index - 1] if index else 0
            if done_s[index] < math.inf:
                message.arrival_s = done_s[index]
                message.delivered_bytes = message.size_bytes
                message.complete = True
            else:
                in_order_segs = max(0, min(rcv_nxt, message_end_seg[index]) - start_byte_seg)
                message.delivered_bytes = min(message.size_bytes, in_order_segs * mss)
                message.lost_ranges = [(message.delivered_bytes, message.size_bytes)]
            if message.deadline_s is not None and message.arrival_s > message.at_s + message.deadline_s:
                # Late data counts as lost: what was in order by the deadline is delivered.
                message.complete = False
                message.arrival_s = math.inf
                deadline_abs_s = message.at_s + message.deadline_s
                in_order_by_deadline = 0
                for when_s, rcv in advances:
                    if when_s > deadline_abs_s:
                        break
                    in_order_by_deadline = rcv
                segs = max(0, min(in_order_by_deadline, message_end_seg[index]) - start_byte_seg)
                message.delivered_bytes = min(message.size_bytes, segs * mss)
                message.lost_ranges = [(message.delivered_bytes, message.size_bytes)]
            message.settled_s = message.arrival_s if message.complete else (
                message.at_s + message.deadline_s if message.deadline_s is not None else math.inf)
        # A transfer cut off by the cap ends the busy period at the cap: later messages start afresh.
        return last_ack_s if una >= n else max(t, last_ack_s)

    def _rtt_sample(self, rtt_s: float, min_rto_s: float, max_rto_s: float) -> None:
        self.min_rtt_s = min(self.min_rtt_s, rtt_s)
        self.srtt_s, self.rttvar_s, self.rto_s = rto_update(self.srtt_s, self.rttvar_s, rtt_s, min_rto_s, max_rto_s)


if __name__ == "__main__":
    from netsim.config import LinkConfig

    env = Environment(seed=0)
    down = Link(env, LinkConfig(bandwidth_mbps=50, delay_ms=17, loss=0.01), "down")
    tcp = TcpConnection(env, down, reverse_delay_s=0.017, config=TcpConfig())
    message = tcp.put(Message(size_bytes=300_000, at_s=0.0))
    print(f"300 kB over 50 Mbit/s, 34 ms RTT, 1 % loss: {message.arrival_s * 1e3:.1f} ms, "
          f"{message.retransmissions} retransmissions, {tcp.timeouts} timeouts")
