"""Discrete-event timeline: stage durations and network deliveries of many clients on one simulated clock.

Pure scheduling, no rendering. A :class:`Group` is one sync frame, one async client frame or one async server
update of one client; its events (stages, modelled stages, messages) have explicit dependencies. The server is
one serial resource shared by every client, and each client is one serial resource of its own: stages on the
same place never overlap, stages on different places do.

The loops (:func:`run_sync`, :func:`run_async`) are a conservative discrete-event simulation. Every client loop
and every server update loop is a coroutine (a greenlet) that runs real work in program order; the scheduler
resumes them in simulated-time order. The network (a netsim topology, where flows of different clients can
share the server's link) is causal: a message sent at time t never changes what arrived before t. So a loop
that needs a message's outcome (its bytes, its losses, its arrival) waits until the simulated clock has reached
the message's arrival: by then every send that could have delayed it has been submitted, and the outcome is
final. A loop never sees a value that a later event could still change.

``docs/method-contract.md`` states the loop rules; the runner feeds the loops real work, the tests synthetic
durations.
"""
from __future__ import annotations

import heapq
import itertools
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import greenlet

PLACES = ("client", "server")
DIRECTIONS = ("down", "up")
PROTOCOLS = ("tcp", "udp")
# Events closer than this are simultaneous: sums of stage times must not flip "arrived by" decisions by rounding.
EPS_S = 1e-9
# Work counters a stage may declare besides rays (counted by the harness) and pixels; the clock's work model
# charges each at a per-unit cost (docs/method-contract.md, "Work counters").
WORK_KINDS = ("pixels", "taps", "points", "codec_bytes")


class SimulationError(RuntimeError):
    """A method broke the rules of the simulation (e.g. read a message inside a stage that does not wait for it)."""


def make_network(spec: str = "ideal", clients: int = 1, server=None, seed: int = 0):
    """A netsim topology: ``clients`` access links of profile ``spec``, optionally sharing a server link."""
    import netsim

    return netsim.make_topology(access=spec, server=server, clients=clients, seed=seed)


def deliver_bytes(payload: bytes | None, size_bytes: int, lost_ranges) -> bytes | None:
    """What the receiver holds of a payload: the sent bytes with every lost range zero-filled.

    The receiver learns which ranges are missing (sequence numbers, the frame's own headers) but never their
    content. ``None`` for a message that carried only a size.
    """
    if payload is None:
        return None
    if not lost_ranges:
        return bytes(payload)
    data = bytearray(payload)
    for start, end in lost_ranges:
        start, end = max(0, int(start)), min(size_bytes, int(end))
        if end > start:
            data[start:end] = bytes(end - start)
    return bytes(data)


# ---------------------------------------------------------------------------------------------------- events

@dataclass(eq=False)
class Event:
    """One scheduled stage or message. ``end_s`` of a message is its arrival (what dependants wait for).

    A message's outcome lives in its netsim delivery and is tentative until the simulated clock reaches it
    (see the module docstring); every field below that derives from it is read from the delivery.
    """

    name: str
    kind: str                   # "stage" | "modelled" | "message"
    place: str                  # client | server for stages; down | up for messages
    loop: str                   # "frame" | "update"
    index: int
    client: int
    ready_s: float              # when its dependencies were satisfied
    start_s: float
    stage_end_s: float = math.nan  # stages: start + duration
    binding: str = ""           # what decided start_s: a dependency name, "<place> busy" or "start"
    rays: int = 0
    pixels: int = 0
    size_bytes: int = 0
    work: dict = field(default_factory=dict)
    protocol: str = ""
    wall_ms: float = float("nan")  # measured wall time of a stage (nan for modelled stages and messages)
    delivery: Any = None
    timeout_s: float = math.inf
    seq: int = 0
    final: bool = False         # a loop has waited for its outcome: it can no longer change

    @property
    def end_s(self) -> float:
        if self.kind != "message":
            return self.stage_end_s
        d = self.delivery
        arrival_s = float(d.arrival_s)
        if math.isfinite(arrival_s):
            return arrival_s
        # An incomplete UDP message is over when its last datagram that could arrive has arrived (netsim's
        # `settled_s`: datagrams carry sequence numbers, so the receiver sees the frame's end). Anything that
        # never settles (a stalled TCP transfer) releases its dependants after a timeout, as a receiver would.
        settled_s = float(getattr(d, "settled_s", math.inf) or math.inf)
        if self.protocol == "udp" and math.isfinite(settled_s):
            return min(settled_s, self.start_s + self.timeout_s)
        return self.start_s + self.timeout_s

    @property
    def complete(self) -> bool:
        if self.kind != "message":
            return True
        return bool(getattr(self.delivery, "complete", True)) and math.isfinite(float(self.delivery.arrival_s))

    @property
    def delivered_bytes(self) -> int:
        return int(self.delivery.delivered_bytes) if self.kind == "message" else 0

    @property
    def lost_bytes(self) -> int:
        return self.size_bytes - self.delivered_bytes if self.kind == "message" else 0

    @property
    def lost_ranges(self) -> list:
        if self.kind != "message":
            return []
        lost = [tuple(r) for r in (getattr(self.delivery, "lost_ranges", None) or [])]
        if not self.complete and not lost and self.delivered_bytes == 0:
            lost = [(0, self.size_bytes)]  # never arrived before the timeout
        return lost

    @property
    def retransmissions(self) -> int:
        return int(getattr(self.delivery, "retransmissions", 0)) if self.kind == "message" else 0

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


# ------------------------------------------------------------------------------------------------- scheduler

class Scheduler:
    """Resumes coroutines (greenlets) in simulated-time order; ties in the order they were queued.

    ``now_s`` only grows. Outside :meth:`run` (direct use of groups in tests) every wait returns at once.
    """

    def __init__(self, network=None):
        self.network = network
        self.now_s = 0.0
        self._heap: list = []
        self._seq = itertools.count()
        self._main: greenlet.greenlet | None = None
        self._blocked: dict = {}  # key -> list of greenlets waiting for a wake-up
        self.on_resume: Callable[[greenlet.greenlet], None] | None = None
        self.loops: list[greenlet.greenlet] = []

    @property
    def running(self) -> bool:
        return self._main is not None and greenlet.getcurrent() is not self._main

    def spawn(self, fn: Callable[[], Any], at_s: float = 0.0, name: str = "") -> greenlet.greenlet:
        g = greenlet.greenlet(fn)
        g.sb_name = name
        self.loops.append(g)
        heapq.heappush(self._heap, (float(at_s), next(self._seq), g))
        return g

    def wait_until(self, t_s: float, always: bool = False) -> None:
        """Suspends the current loop until ``t_s``; with ``always`` it also yields when ``t_s`` is now, behind the
        loops already queued for this instant."""
        if not self.running or (t_s <= self.now_s + EPS_S and not always):
            return
        heapq.heappush(self._heap, (max(float(t_s), self.now_s), next(self._seq), greenlet.getcurrent()))
        self._main.switch()

    def block(self, key) -> None:
        """Suspends the current loop until :meth:`wake` is called with ``key``."""
        if not self.running:
            raise SimulationError(f"a loop blocked on {key!r} outside the scheduler")
        self._blocked.setdefault(key, []).append(greenlet.getcurrent())
        self._main.switch()

    def wake(self, key, at_s: float) -> None:
        for g in self._blocked.pop(key, []):
            heapq.heappush(self._heap, (max(float(at_s), self.now_s), next(self._seq), g))

    def run(self) -> None:
        self._main = greenlet.getcurrent()
        try:
            while self._heap:
                t_s, _, g = heapq.heappop(self._heap)
                if g.dead:
                    continue
                if t_s > self.now_s:
                    self.now_s = t_s
                    if self.network is not None and hasattr(self.network, "advance"):
                        # netsim may forget what happened before the frontier: no send will precede it.
                        self.network.advance(self.now_s)
                if self.on_resume is not None:
                    self.on_resume(g)
                g.switch()
        finally:
            self._main = None
        stuck = [g.sb_name for g in self.loops if not g.dead and not getattr(g, "sb_may_block", False)]
        if stuck:
            raise SimulationError(f"simulation ended with loops still waiting: {', '.join(stuck)}")


class Timeline:
    """The simulated clock, the places (one server, one per client) and the network of one frame sequence.

    ``network`` is a netsim topology (``send(size, client=, direction=, protocol=, at_s=, deadline_s=)``,
    ``advance(t)``); the default is netsim's ``ideal`` profile.
    """

    def __init__(self, network=None, message_timeout_s: float = 0.1, clients: int = 1):
        self.clients = int(clients)
        self.network = network if network is not None else make_network("ideal", clients=self.clients)
        self.message_timeout_s = float(message_timeout_s)
        self.sched = Scheduler(self.network)
        self.free_s: dict[str, float] = {}
        self.holder: dict[str, tuple] = {}  # place key -> (group, event name) that last occupied it
        self.last_send_s: dict[tuple, float] = {}
        self.reordered_sends = 0
        self.events: list[Event] = []
        self._seq = itertools.count()
        self.on_message: Callable[[Event, "Group"], None] | None = None

    @staticmethod
    def place_key(place: str, client: int) -> str:
        return "server" if place == "server" else f"client{client}"

    def server_free_s(self) -> float:
        return self.free_s.get("server", 0.0)

    def group(self, loop: str, index: int, start_s: float, client: int = 0) -> "Group":
        if not 0 <= int(client) < self.clients:
            raise ValueError(f"client {client} out of range (this timeline has {self.clients})")
        return Group(self, loop, index, start_s, int(client))

    def wait_final(self, ev: Event) -> None:
        """Waits (inside the simulation) until ``ev``'s outcome can no longer change."""
        if not self.sched.running:
            return
        if ev.kind == "message" and not ev.final:
            # First let every loop that is due before the send (or at the same instant) submit its sends: a
            # message cannot arrive before it was sent, and reading a tentative outcome that those sends would
            # change costs the network model a re-simulation.
            self.sched.wait_until(ev.start_s, always=True)
        while ev.end_s > self.sched.now_s + EPS_S:
            self.sched.wait_until(ev.end_s)
        ev.final = True

    def is_final(self, ev: Event) -> bool:
        return not self.sched.running or ev.final or ev.end_s <= self.sched.now_s + EPS_S

    def _send(self, size_bytes: int, client: int, direction: str, protocol: str, ready_s: float):
        # One client's sends in one direction form one ordered stream: a send whose ready time precedes an
        # earlier send of the same stream queues behind it. Streams of different clients are independent.
        key = (client, direction)
        at_s = ready_s
        if at_s < self.last_send_s.get(key, 0.0):
            at_s = self.last_send_s[key]
            self.reordered_sends += 1
        self.last_send_s[key] = at_s
        # The receiver gives a UDP message up after the timeout: datagrams arriving later count as lost, so a
        # method never uses data that came after it stopped waiting.
        deadline_s = self.message_timeout_s if protocol == "udp" else None
        return at_s, self.network.send(int(size_bytes), client=client, direction=direction, protocol=protocol,
                                       at_s=at_s, deadline_s=deadline_s)


class Group:
    """The events of one frame or update of one client, scheduled in program order."""

    def __init__(self, timeline: Timeline, loop: str, index: int, start_s: float, client: int = 0):
        self.timeline = timeline
        self.loop = loop
        self.index = index
        self.client = client
        self.start_s = float(start_s)
        self.floor_s = self.start_s
        self.events: dict[str, Event] = {}
        self._last: str | None = None

    def _ready(self, name: str, after) -> tuple[float, str]:
        if name in self.events:
            raise ValueError(f"event name '{name}' used twice in {self.loop} {self.index}")
        deps = self.dependencies(name, after)
        ready_s, binding = self.floor_s, "start"
        for dep in deps:
            ev = self.events[dep]
            self.timeline.wait_final(ev)
            if ev.end_s > ready_s:
                ready_s, binding = ev.end_s, dep
        return ready_s, binding

    def dependencies(self, name: str, after) -> list[str]:
        if after is None:
            after = [self._last] if self._last is not None else []
        elif isinstance(after, str):
            after = [after]
        for dep in after:
            if dep not in self.events:
                raise ValueError(f"'{name}' depends on unknown event '{dep}' in {self.loop} {self.index}")
        return list(after)

    def hold_until(self, t_s: float) -> None:
        """No later event of this group starts before ``t_s`` (a lockstep barrier)."""
        self.floor_s = max(self.floor_s, float(t_s))

    def restart_chain(self) -> None:
        """The next event with ``after=None`` starts from the group's start, not after the previous event."""
        self._last = None

    def add_stage(self, name: str, place: str, duration_s: float, after=None, kind: str = "stage",
                  rays: int = 0, pixels: int = 0, size_bytes: int = 0, wall_ms: float = float("nan"),
                  work: dict | None = None) -> Event:
        if place not in PLACES:
            raise ValueError(f"stage '{name}': place must be one of {PLACES}, not {place!r}")
        if not duration_s >= 0:
            raise ValueError(f"stage '{name}': duration must be >= 0, got {duration_s}")
        ready_s, binding = self._ready(name, after)
        tl = self.timeline
        key = tl.place_key(place, self.client)
        start_s = ready_s
        if tl.free_s.get(key, 0.0) > start_s:
            holder = tl.holder.get(key)
            # Within one group the event that held the place continues the critical path.
            binding = holder[1] if holder is not None and holder[0] is self else f"{place} busy"
            start_s = tl.free_s[key]
        ev = Event(name, kind, place, self.loop, self.index, self.client, ready_s, start_s, start_s + duration_s,
                   binding, rays=int(rays), pixels=int(pixels), size_bytes=int(size_bytes),
                   work={k: int(v) for k, v in (work or {}).items()}, wall_ms=wall_ms, seq=next(tl._seq))
        tl.free_s[key] = ev.stage_end_s
        tl.holder[key] = (self, name)
        return self._add(ev)

    def add_message(self, name: str, size_bytes: int, direction: str, protocol: str = "tcp", after=None):
        """Schedules a message of this group's client; returns (event, delivery)."""
        if direction not in DIRECTIONS:
            raise ValueError(f"message '{name}': direction must be one of {DIRECTIONS}, not {direction!r}")
        if protocol not in PROTOCOLS:
            raise ValueError(f"message '{name}': protocol must be one of {PROTOCOLS}, not {protocol!r}")
        if int(size_bytes) <= 0:
            raise ValueError(f"message '{name}': size must be > 0 bytes, got {size_bytes}")
        ready_s, binding = self._ready(name, after)
        sent_s, d = self.timeline._send(size_bytes, self.client, direction, protocol, ready_s)
        if sent_s > ready_s:
            binding = f"{direction} queue"
        ev = Event(name, "message", direction, self.loop, self.index, self.client, ready_s, sent_s,
                   binding=binding, size_bytes=int(size_bytes), protocol=protocol, delivery=d,
                   timeout_s=self.timeline.message_timeout_s, seq=next(self.timeline._seq))
        self._add(ev)
        if self.timeline.on_message is not None:
            self.timeline.on_message(ev, self)
        return ev, d

    def _add(self, ev: Event) -> Event:
        self.events[ev.name] = ev
        self._last = ev.name
        self.timeline.events.append(ev)
        return ev

    @property
    def end_s(self) -> float:
        return max((e.end_s for e in self.events.values()), default=self.start_s)

    def display_event(self) -> Event | None:
        """The client stage that ends last: the frame is on screen when it ends (messages the client sent, such
        as its pose, are not part of the frame)."""
        client_stages = [e for e in self.events.values() if e.kind != "message" and e.place == "client"]
        return max(client_stages, key=lambda e: (e.end_s, e.seq)) if client_stages else None

    @property
    def display_s(self) -> float:
        ev = self.display_event()
        return ev.end_s if ev is not None else self.end_s

    def critical_path(self, until: Event | None = None) -> list[str]:
        """Names of the events on the path that decided ``until``'s end (default: the group's last event)."""
        if not self.events:
            return []
        ev = until or max(self.events.values(), key=lambda e: (e.end_s, e.seq))
        path = [ev.name]
        while ev.binding in self.events:
            ev = self.events[ev.binding]
            path.append(ev.name)
        return path[::-1]

    def critical_path_ms(self, until: Event | None = None) -> dict:
        """{event name: ms} along the critical path, plus "wait" for any time not covered by an event.

        The values sum to the span from the group's start to ``until``'s end, so a stacked bar of them is the
        frame time.
        """
        path = self.critical_path(until)
        out = {name: 1e3 * self.events[name].duration_s for name in path}
        end_s = (until.end_s if until is not None else self.end_s)
        wait_ms = 1e3 * (end_s - self.start_s) - sum(out.values())
        if wait_ms > 1e-9:
            out["wait"] = wait_ms
        return out

    def summary(self) -> dict:
        """Per-group totals: client/server busy time, network time, bytes, rays, work counters."""
        ev = list(self.events.values())
        msgs = [e for e in ev if e.kind == "message"]
        out = {
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
        for kind in WORK_KINDS[1:]:
            out[f"work_{kind}"] = sum(e.work.get(kind, 0) for e in ev)
        return out


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
    client: int = 0


@dataclass
class UpdateTiming:
    index: int
    start_s: float
    input_s: float          # when the client sampled the input it reflects (the start of the frame that sent it)
    input_frame: int = -1   # that client frame's index
    group: Group | None = None
    value: Any = None
    client: int = 0
    done: bool = False      # the update's code has run to its end (its events are all scheduled)

    @property
    def arrival_s(self) -> float:
        return self.group.end_s

    @property
    def update_ms(self) -> float:
        return 1e3 * (self.arrival_s - self.start_s)


@dataclass
class ClientInput:
    """What the server has received from one client for one update: the up messages that arrived since the
    previous update (oldest first), each with the client frame that sent it."""

    messages: list  # [(Event, frame index, frame start s)]

    @property
    def newest(self):
        return self.messages[-1]


def _finish_frame(frames: list, i: int, start_s: float, g: Group, value, client: int, used=None,
                  lockstep_start_s: float | None = None) -> FrameTiming:
    display_ev = g.display_event()
    if display_ev is None:
        for ev in g.events.values():
            g.timeline.wait_final(ev)
    display_s = g.display_s
    frame_ms = 1e3 * (display_s - start_s)
    latency_ms = frame_ms
    if lockstep_start_s is not None:
        # the input of a zero-latency frame is sampled when its update starts
        frame_ms = latency_ms = 1e3 * (display_s - lockstep_start_s)
    interval_ms = 1e3 * (display_s - frames[-1].display_s) if frames else float("nan")
    staleness_ms = 1e3 * (display_s - used.input_s) if used is not None else float("nan")
    f = FrameTiming(i, start_s, display_s, frame_ms, latency_ms, interval_ms, staleness_ms,
                    used.index if used is not None else -1, group=g, value=value, client=client)
    frames.append(f)
    return f


def run_sync(timeline: Timeline, n_frames: int, period_s: float, run_frame: Callable[[Group], Any],
             clients: int | None = None) -> list[FrameTiming]:
    """Synchronous loops, one per client: frame i starts at max(i * period, previous display) and is displayed
    when its last client stage ends. Returns the frames of every client, ordered by (client, index)."""
    clients = timeline.clients if clients is None else int(clients)
    per_client: list[list[FrameTiming]] = [[] for _ in range(clients)]

    def loop(c: int):
        frames = per_client[c]
        prev_display_s = 0.0
        for i in range(n_frames):
            start_s = max(i * period_s, prev_display_s)
            timeline.sched.wait_until(start_s)
            g = timeline.group("frame", i, start_s, client=c)
            value = run_frame(g)
            prev_display_s = _finish_frame(frames, i, start_s, g, value, c).display_s

    for c in range(clients):
        timeline.sched.spawn(lambda c=c: loop(c), 0.0, name=f"client {c}")
    timeline.sched.run()
    return [f for frames in per_client for f in frames]


def run_async(timeline: Timeline, n_frames: int, client_period_s: float,
              run_update: Callable[[Group, ClientInput], Any],
              run_frame: Callable[[Group, UpdateTiming | None], Any],
              run_input: Callable[[Group], Any] | None = None,
              max_in_flight: int = 1, update_period_s: float = 0.0, lockstep: bool = False,
              clients: int | None = None):
    """Asynchronous loops: per client, a client loop and a server update loop on one clock.

    Client loop: frame i starts at max(i * client_period, previous display); it first runs ``run_input(group)``
    (what the client sends the server: its pose, requests), then ``run_frame(group, update)`` with the newest
    update of this client that has ARRIVED by the frame's start.

    Update loop: update k starts when (a) input from its client has arrived that no earlier update used,
    (b) k * update_period has passed, (c) update k - max_in_flight has arrived, and (d) the shared server is
    free. ``run_update(group, inputs)`` does the update from what the server received; the update has arrived
    when its last event has ended. Updates stop once their client has started its last frame.

    With ``lockstep`` (zero-latency), each client frame's input is handed to an update at once and the frame
    uses that update. Returns (frames, updates), each ordered by (client, index).
    """
    if max_in_flight < 1:
        raise ValueError("max_in_flight must be >= 1")
    clients = timeline.clients if clients is None else int(clients)
    frames: list[list[FrameTiming]] = [[] for _ in range(clients)]
    updates: list[list[UpdateTiming]] = [[] for _ in range(clients)]
    inputs: list[list] = [[] for _ in range(clients)]   # (event, frame index, frame start s) per client
    state = [{"started_last": False, "frame": -1, "frame_start_s": 0.0} for _ in range(clients)]
    sched = timeline.sched

    def on_message(ev: Event, g: Group):
        # Up messages of a client frame are that client's input to the server.
        if ev.place == "up" and g.loop == "frame":
            inputs[g.client].append((ev, g.index, g.start_s))
            sched.wake(("input", g.client), ev.end_s)

    timeline.on_message = on_message

    def do_update(c: int, start_s: float, new_inputs: list) -> UpdateTiming:
        k = len(updates[c])
        g = timeline.group("update", k, start_s, client=c)
        ev, frame_i, frame_start_s = new_inputs[-1]
        u = UpdateTiming(k, start_s, frame_start_s, frame_i, group=g, client=c)
        updates[c].append(u)
        u.value = run_update(g, ClientInput(list(new_inputs)))
        u.done = True
        return u

    def client_loop(c: int):
        prev_display_s = 0.0
        used_inputs = 0
        for i in range(n_frames):
            start_s = max(i * client_period_s, prev_display_s)
            sched.wait_until(start_s)
            st = state[c]
            st["frame"], st["frame_start_s"] = i, start_s
            st["started_last"] = i == n_frames - 1
            g = timeline.group("frame", i, start_s, client=c)
            if run_input is not None:
                run_input(g)
                g.restart_chain()
            lockstep_start_s = None
            if lockstep:
                new = inputs[c][used_inputs:]
                if not new:
                    raise SimulationError("a zero-latency client frame sent no input to the server")
                used_inputs = len(inputs[c])
                u_start_s = max(start_s, max(ev.end_s for ev, _, _ in new), timeline.server_free_s())
                used = do_update(c, u_start_s, new)
                for ev in used.group.events.values():
                    timeline.wait_final(ev)
                g.hold_until(used.arrival_s)
                lockstep_start_s = u_start_s
            else:
                arrived = [u for u in updates[c] if u.done and u.arrival_s <= start_s + EPS_S]
                used = max(arrived, key=lambda u: u.index) if arrived else None
            value = run_frame(g, used)
            prev_display_s = _finish_frame(frames[c], i, start_s, g, value, c, used, lockstep_start_s).display_s

    def update_loop(c: int):
        consumed: set[int] = set()  # event seqs of this client's inputs used by earlier updates
        while True:
            k = len(updates[c])
            t_s = k * update_period_s
            if k >= max_in_flight:
                prev = updates[c][k - max_in_flight]
                for ev in prev.group.events.values():
                    timeline.wait_final(ev)
                t_s = max(t_s, prev.arrival_s)
            sched.wait_until(t_s)
            while True:
                if state[c]["started_last"]:
                    return  # no frame of this client can show a later update
                new = [x for x in inputs[c] if x[0].seq not in consumed]
                # (a message sent after now cannot have arrived: only those sent before are asked for)
                arrived = [x for x in new if x[0].start_s <= sched.now_s and x[0].end_s <= sched.now_s + EPS_S]
                if arrived and timeline.server_free_s() <= sched.now_s + EPS_S:
                    break
                if arrived:
                    sched.wait_until(timeline.server_free_s())
                elif new:
                    sched.wait_until(min(x[0].end_s for x in new))
                else:
                    sched.block(("input", c))
            consumed.update(x[0].seq for x in arrived)
            do_update(c, sched.now_s, arrived)

    for c in range(clients):
        sched.spawn(lambda c=c: client_loop(c), 0.0, name=f"client {c}")
    if not lockstep:
        for c in range(clients):
            g = sched.spawn(lambda c=c: update_loop(c), 0.0, name=f"updates {c}")
            g.sb_may_block = True  # waits for input that may never come once its client is done
    sched.run()
    return [f for fs in frames for f in fs], [u for us in updates for u in us]
