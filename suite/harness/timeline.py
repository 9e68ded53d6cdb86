"""Discrete-event timeline: stage durations and network deliveries on one simulated clock.

Pure scheduling, no rendering. A :class:`Group` is one sync frame, one async client frame or one async server
update; its events (stages, modelled stages, messages) have explicit dependencies. ``client`` and ``server`` are
each one serial resource, so stages on the same place never overlap and stages on different places do.

:func:`run_sync` and :func:`run_async` drive the two loop shapes described in ``docs/method-contract.md``;
the runner feeds them real work, the tests synthetic durations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

PLACES = ("client", "server")
DIRECTIONS = ("down", "up")
PROTOCOLS = ("tcp", "udp")
# Events closer than this are simultaneous: sums of stage times must not flip "arrived by" decisions by rounding.
EPS_S = 1e-9


# --------------------------------------------------------------------------------------------------- network

@dataclass
class Delivery:
    """What the link did with one message (the fields netsim's deliveries also carry)."""

    arrival_s: float
    delivered_bytes: int
    lost_ranges: list = field(default_factory=list)
    retransmissions: int = 0
    complete: bool = True


class IdealLink:
    """Fallback link while netsim is absent: arrival = send + delay + size / bandwidth, no loss.

    ``bandwidth_mbps = inf`` and ``delay_ms = 0`` is the ``ideal`` network of the zero-latency run.
    """

    def __init__(self, bandwidth_mbps: float = math.inf, delay_ms: float = 0.0):
        if not bandwidth_mbps > 0 or delay_ms < 0:
            raise ValueError("link needs bandwidth > 0 and delay >= 0")
        self.bandwidth_mbps = float(bandwidth_mbps)
        self.delay_ms = float(delay_ms)

    def send(self, size_bytes: int, direction: str = "down", protocol: str = "tcp", at_s: float = 0.0,
             deadline_s: float | None = None) -> Delivery:
        transfer_s = 0.0 if math.isinf(self.bandwidth_mbps) else size_bytes * 8.0 / (self.bandwidth_mbps * 1e6)
        arrival_s = at_s + self.delay_ms / 1e3 + transfer_s
        if deadline_s is not None and arrival_s > at_s + deadline_s:
            # Too late: the receiver stopped waiting (the whole message counts as lost).
            return Delivery(arrival_s=math.inf, delivered_bytes=0, lost_ranges=[(0, int(size_bytes))], complete=False)
        return Delivery(arrival_s=arrival_s, delivered_bytes=int(size_bytes))

    def describe(self) -> str:
        return f"ideal link: bw={self.bandwidth_mbps} Mbit/s, delay={self.delay_ms} ms"


# ---------------------------------------------------------------------------------------------------- events

@dataclass
class Event:
    """One scheduled stage or message. ``end_s`` of a message is its arrival (what dependants wait for)."""

    name: str
    kind: str                   # "stage" | "modelled" | "message"
    place: str                  # client | server for stages; down | up for messages
    loop: str                   # "frame" | "update"
    index: int
    ready_s: float              # when its dependencies were satisfied
    start_s: float
    end_s: float
    binding: str = ""           # what decided start_s: a dependency name, "<place> busy" or "start"
    rays: int = 0
    pixels: int = 0
    size_bytes: int = 0
    delivered_bytes: int = 0
    lost_bytes: int = 0
    retransmissions: int = 0
    complete: bool = True
    protocol: str = ""
    wall_ms: float = float("nan")  # measured wall time of a stage (nan for modelled stages and messages)

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


class Timeline:
    """The simulated clock, the two serial resources and the links (one per direction)."""

    def __init__(self, links: dict | None = None, message_timeout_s: float = 0.1):
        ideal = IdealLink()
        self.links = links or {"down": ideal, "up": ideal}
        self.message_timeout_s = float(message_timeout_s)
        self.free_s = {p: 0.0 for p in PLACES}
        self.holder = {p: None for p in PLACES}  # (group, event name) that last occupied each place
        self.last_send_s = {d: 0.0 for d in DIRECTIONS}
        self.reordered_sends = 0
        self.events: list[Event] = []

    def group(self, loop: str, index: int, start_s: float) -> "Group":
        return Group(self, loop, index, start_s)

    def _send(self, size_bytes: int, direction: str, protocol: str, ready_s: float):
        # A link is a FIFO queue that must see sends in time order; a send whose ready time precedes an earlier
        # send in the same direction queues behind it.
        at_s = ready_s
        if at_s < self.last_send_s[direction]:
            at_s = self.last_send_s[direction]
            self.reordered_sends += 1
        self.last_send_s[direction] = at_s
        if protocol == "udp":
            # The receiver gives a UDP message up after the timeout: datagrams arriving later count as lost,
            # so a method never uses data that came after it stopped waiting.
            return at_s, self.links[direction].send(int(size_bytes), direction=direction, protocol=protocol, at_s=at_s,
                                                    deadline_s=self.message_timeout_s)
        return at_s, self.links[direction].send(int(size_bytes), direction=direction, protocol=protocol, at_s=at_s)


class Group:
    """The events of one frame or update, scheduled in program order."""

    def __init__(self, timeline: Timeline, loop: str, index: int, start_s: float):
        self.timeline = timeline
        self.loop = loop
        self.index = index
        self.start_s = float(start_s)
        self.events: dict[str, Event] = {}
        self._last: str | None = None

    def _ready(self, name: str, after) -> tuple[float, str]:
        if name in self.events:
            raise ValueError(f"event name '{name}' used twice in {self.loop} {self.index}")
        if after is None:
            after = [self._last] if self._last is not None else []
        elif isinstance(after, str):
            after = [after]
        ready_s, binding = self.start_s, "start"
        for dep in after:
            if dep not in self.events:
                raise ValueError(f"'{name}' depends on unknown event '{dep}' in {self.loop} {self.index}")
            if self.events[dep].end_s > ready_s:
                ready_s, binding = self.events[dep].end_s, dep
        return ready_s, binding

    def add_stage(self, name: str, place: str, duration_s: float, after=None, kind: str = "stage",
                  rays: int = 0, pixels: int = 0, size_bytes: int = 0, wall_ms: float = float("nan")) -> Event:
        if place not in PLACES:
            raise ValueError(f"stage '{name}': place must be one of {PLACES}, not {place!r}")
        if not duration_s >= 0:
            raise ValueError(f"stage '{name}': duration must be >= 0, got {duration_s}")
        ready_s, binding = self._ready(name, after)
        start_s = ready_s
        if self.timeline.free_s[place] > start_s:
            holder = self.timeline.holder[place]
            # Within one group the event that held the place continues the critical path.
            binding = holder[1] if holder is not None and holder[0] is self else f"{place} busy"
            start_s = self.timeline.free_s[place]
        ev = Event(name, kind, place, self.loop, self.index, ready_s, start_s, start_s + duration_s, binding,
                   rays=int(rays), pixels=int(pixels), size_bytes=int(size_bytes), wall_ms=wall_ms)
        self.timeline.free_s[place] = ev.end_s
        self.timeline.holder[place] = (self, name)
        return self._add(ev)

    def add_message(self, name: str, size_bytes: int, direction: str, protocol: str = "tcp", after=None):
        """Schedules a message; returns (event, delivery)."""
        if direction not in DIRECTIONS:
            raise ValueError(f"message '{name}': direction must be one of {DIRECTIONS}, not {direction!r}")
        if protocol not in PROTOCOLS:
            raise ValueError(f"message '{name}': protocol must be one of {PROTOCOLS}, not {protocol!r}")
        if int(size_bytes) < 0:
            raise ValueError(f"message '{name}': size must be >= 0")
        ready_s, binding = self._ready(name, after)
        sent_s, d = self.timeline._send(size_bytes, direction, protocol, ready_s)
        if sent_s > ready_s:
            binding = f"{direction} queue"
        arrival_s = float(d.arrival_s)
        # An incomplete UDP message is over when its last datagram that could arrive has arrived (netsim's
        # `settled_s`: datagrams carry sequence numbers, so the receiver sees the frame's end). Anything that
        # never settles (a stalled TCP transfer) releases its dependants after a timeout, as a receiver would.
        settled_s = float(getattr(d, "settled_s", math.inf) or math.inf)
        if math.isfinite(arrival_s):
            end_s = arrival_s
        elif protocol == "udp" and math.isfinite(settled_s):
            end_s = min(settled_s, sent_s + self.timeline.message_timeout_s)
        else:
            end_s = sent_s + self.timeline.message_timeout_s
        delivered = int(d.delivered_bytes)
        ev = Event(name, "message", direction, self.loop, self.index, ready_s, sent_s, end_s, binding,
                   size_bytes=int(size_bytes), delivered_bytes=delivered, lost_bytes=int(size_bytes) - delivered,
                   retransmissions=int(getattr(d, "retransmissions", 0)),
                   complete=bool(getattr(d, "complete", True)) and math.isfinite(arrival_s), protocol=protocol)
        return self._add(ev), d

    def _add(self, ev: Event) -> Event:
        self.events[ev.name] = ev
        self._last = ev.name
        self.timeline.events.append(ev)
        return ev

    @property
    def end_s(self) -> float:
        return max((e.end_s for e in self.events.values()), default=self.start_s)

    def critical_path(self) -> list[str]:
        """Names of the events on the path that decided the end time, first to last."""
        if not self.events:
            return []
        ev = max(self.events.values(), key=lambda e: e.end_s)
        path = [ev.name]
        while ev.binding in self.events:
            ev = self.events[ev.binding]
            path.append(ev.name)
        return path[::-1]

    def critical_path_ms(self) -> dict:
        """{event name: ms} along the critical path, plus "wait" for any time not covered by an event.

        The values sum to the group's span (end - start), so a stacked bar of them is the frame time.
        """
        out = {name: 1e3 * self.events[name].duration_s for name in self.critical_path()}
        covered = sum(out.values())
        wait_ms = 1e3 * (self.end_s - self.start_s) - covered
        if wait_ms > 1e-9:
            out["wait"] = wait_ms
        return out

    def summary(self) -> dict:
        """Per-group totals: client/server busy time, network time, bytes, rays."""
        ev = list(self.events.values())
        msgs = [e for e in ev if e.kind == "message"]
        return {
            "client_ms": 1e3 * sum(e.duration_s for e in ev if e.place == "client"),
            "server_ms": 1e3 * sum(e.duration_s for e in ev if e.place == "server"),
            "network_ms": 1e3 * sum(e.duration_s for e in msgs),
            "bytes_down": sum(e.size_bytes for e in msgs if e.place == "down"),
            "bytes_up": sum(e.size_bytes for e in msgs if e.place == "up"),
            "lost_bytes": sum(e.lost_bytes for e in msgs),
            "retransmissions": sum(e.retransmissions for e in msgs),
            "messages": len(msgs),
            "rays": sum(e.rays for e in ev),
            "pixels": sum(e.pixels for e in ev),
        }


# ----------------------------------------------------------------------------------------------------- loops

@dataclass
class FrameTiming:
    """Timing of one client frame (one row of frames.parquet, before the method's own columns)."""

    index: int
    start_s: float
    display_s: float
    frame_ms: float
    latency_ms: float
    frame_interval_ms: float
    staleness_ms: float = float("nan")
    update_index: int = -1
    group: Group | None = None
    value: Any = None


@dataclass
class UpdateTiming:
    index: int
    start_s: float
    input_s: float          # when the input it reflects was sampled (snapped to a client frame start)
    arrival_s: float
    group: Group | None = None
    value: Any = None

    @property
    def update_ms(self) -> float:
        return 1e3 * (self.arrival_s - self.start_s)


def run_sync(timeline: Timeline, n_frames: int, period_s: float,
             run_frame: Callable[[Group], Any]) -> list[FrameTiming]:
    """Synchronous loop: frame i starts at max(i * period, previous display) and ends at its critical path."""
    frames: list[FrameTiming] = []
    prev_display_s = 0.0
    for i in range(n_frames):
        start_s = max(i * period_s, prev_display_s)
        g = timeline.group("frame", i, start_s)
        value = run_frame(g)
        display_s = g.end_s
        frame_ms = 1e3 * (display_s - start_s)
        interval_ms = 1e3 * (display_s - frames[-1].display_s) if frames else float("nan")
        frames.append(FrameTiming(i, start_s, display_s, frame_ms, frame_ms, interval_ms, group=g, value=value))
        prev_display_s = display_s
    return frames


def run_async(timeline: Timeline, n_frames: int, client_period_s: float,
              run_update: Callable[[Group, float], Any],
              run_frame: Callable[[Group, UpdateTiming | None], Any],
              max_in_flight: int = 1, update_period_s: float = 0.0, lockstep: bool = False):
    """Asynchronous loops: the client at its own rate using the newest ARRIVED update; updates as their own loop.

    Update k starts at max(k * update_period, server free, arrival of update k - max_in_flight, the client
    frame after the previous update's input).

    ``run_update(group, input_s)`` does one server update whose input was sampled at ``input_s``;
    ``run_frame(group, update)`` one client frame. With ``lockstep`` (zero-latency), each client frame first
    gets an update made at its own start, and uses it whatever its arrival. Returns (frames, updates).
    """
    if max_in_flight < 1:
        raise ValueError("max_in_flight must be >= 1")
    frames: list[FrameTiming] = []
    updates: list[UpdateTiming] = []

    def snap(t_s: float) -> float:
        # The client samples its input once per frame, so an update sees the newest frame start at or before it.
        if client_period_s <= 0:
            return t_s
        return math.floor(t_s / client_period_s + 1e-9) * client_period_s

    def do_update(start_s: float, input_s: float) -> UpdateTiming:
        g = timeline.group("update", len(updates), start_s)
        value = run_update(g, input_s)
        u = UpdateTiming(len(updates), start_s, input_s, g.end_s, group=g, value=value)
        updates.append(u)
        return u

    def next_update_start() -> float:
        k = len(updates)
        t = k * update_period_s
        if k >= max_in_flight:
            t = max(t, updates[k - max_in_flight].arrival_s)
        if updates and client_period_s > 0:
            # The client's input changes once per frame: a second update on the same input would repeat the
            # first (and a zero-cost update could otherwise repeat forever).
            t = max(t, updates[-1].input_s + client_period_s)
        return max(t, timeline.free_s["server"])

    prev_display_s = 0.0
    for i in range(n_frames):
        start_s = max(i * client_period_s, prev_display_s)
        if lockstep:
            used = do_update(start_s, start_s)
            start_s = used.arrival_s
        else:
            while True:
                u_start_s = next_update_start()
                if not u_start_s <= start_s + EPS_S:
                    break
                do_update(u_start_s, snap(u_start_s))
            arrived = [u for u in updates if u.arrival_s <= start_s + EPS_S]
            used = max(arrived, key=lambda u: u.index) if arrived else None
        g = timeline.group("frame", i, start_s)
        value = run_frame(g, used)
        display_s = g.end_s
        frame_ms = 1e3 * (display_s - start_s)
        interval_ms = 1e3 * (display_s - frames[-1].display_s) if frames else float("nan")
        staleness_ms = 1e3 * (display_s - used.input_s) if used is not None else float("nan")
        if lockstep:
            # the input of a zero-latency frame is sampled when its update starts
            frame_ms = latency_ms = 1e3 * (display_s - used.start_s)
        else:
            latency_ms = frame_ms
        frames.append(FrameTiming(i, start_s, display_s, frame_ms, latency_ms, interval_ms, staleness_ms,
                                  used.index if used is not None else -1, group=g, value=value))
        prev_display_s = display_s
    return frames, updates
