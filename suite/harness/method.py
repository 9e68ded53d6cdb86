"""The method contract: the base class a pipeline subclasses, and the context it runs its stages in.

See ``docs/method-contract.md`` for the full contract (stages, messages, the simulated clock, config.toml).
"""
from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from suite.harness.timeline import Group


class Method:
    """Base class of a split-rendering pipeline.

    Subclasses set ``name`` (= folder name) and ``mode`` and implement ``frame`` (sync) or ``server_update`` and
    ``client_frame`` (async). ``prepare`` is offline precomputation, timed separately.
    """

    name: str = ""
    mode: str = "sync"          # "sync" | "async"
    uses_network: bool = True   # False: the zero-latency run would be identical, so the harness skips it

    def __init__(self, params: dict):
        self.params = dict(params)

    def prepare(self, scene, tracer) -> None:
        """Offline precomputation before the first frame (timed as prepare_ms)."""

    def reset(self) -> None:
        """Clears per-sequence state; called before each frame sequence (the run, then its zero-latency run)."""

    def frame(self, ctx: "Context") -> np.ndarray:
        """Sync: one client frame; returns the displayed image, float32 (H, W, 3)."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'sync' but does not implement frame()")

    def server_update(self, ctx: "Context"):
        """Async: one server update; returns what the client may use once it has arrived."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'async' but does not implement server_update()")

    def client_frame(self, ctx: "Context", update) -> np.ndarray:
        """Async: one client frame with the newest arrived update (None before the first)."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'async' but does not implement client_frame()")

    def __str__(self) -> str:
        args = ",".join(f"{k}={self.params[k]}" for k in sorted(self.params))
        return f"{self.name}({args})"


@dataclass
class StageRecord:
    """Counters of one stage; the method may set ``pixels`` and ``bytes`` inside the block."""

    name: str
    place: str
    pixels: int = 0
    bytes: int = 0
    rays: int = 0
    wall_ms: float = float("nan")


@dataclass
class Message:
    """A message after the network handled it."""

    name: str
    size_bytes: int
    direction: str
    protocol: str
    sent_s: float
    arrival_s: float
    delivered_bytes: int
    lost_ranges: list = field(default_factory=list)
    retransmissions: int = 0
    complete: bool = True
    payload: bytes | None = None

    @property
    def transfer_ms(self) -> float:
        return 1e3 * (self.arrival_s - self.sent_s)


@dataclass
class Clock:
    """Where stage durations come from: measured wall time, or a work model (machine-independent)."""

    source: str = "measured"        # "measured" | "work"
    work_ns_per_ray: float = 50.0
    work_ns_per_pixel: float = 20.0

    def duration_s(self, wall_s: float, rays: int, pixels: int) -> float:
        if self.source == "work":
            return 1e-9 * (rays * self.work_ns_per_ray + pixels * self.work_ns_per_pixel)
        return wall_s


def _ray_count(tracer) -> int:
    counters = getattr(tracer, "counters", None) or {}
    return int(counters.get("rays_intersect", 0)) + int(counters.get("rays_occluded", 0))


class Context:
    """What a method sees during one frame or update. See docs/method-contract.md for the attributes."""

    def __init__(self, group: Group, *, scene, tracer, t_s: float, prev_t_s, resolution, seed: int,
                 params: dict, zero_latency: bool, protocol: str = "tcp", clock: Clock | None = None,
                 update_index: int = -1, update_t_s: float | None = None, update_is_new: bool = False):
        self.group = group
        self.scene = scene
        self.tracer = tracer
        self.t_s = t_s
        self.prev_t_s = prev_t_s
        self.resolution = tuple(resolution)
        self.loop = group.loop
        self.index = group.index
        self.params = params
        self.zero_latency = zero_latency
        self.protocol = protocol
        self.clock = clock or Clock()
        loop_id = 0 if group.loop == "frame" else 1
        # One independent stream per (run seed, loop, index): reruns and other frames do not shift it.
        self.seed = int(np.random.SeedSequence([int(seed), loop_id, int(group.index)]).generate_state(1)[0])
        self.rng = np.random.default_rng(self.seed)
        self.update_index = update_index
        self.update_t_s = update_t_s
        self.update_is_new = update_is_new
        self.stages: list[StageRecord] = []
        self.messages: list[Message] = []

    @contextmanager
    def stage(self, name: str, place: str, after=None):
        """Runs the block as a stage on ``place``; times it and counts rays (tracer counter deltas)."""
        rec = StageRecord(name, place)
        rays0 = _ray_count(self.tracer)
        t0 = time.perf_counter()
        yield rec
        wall_s = time.perf_counter() - t0
        rec.rays = _ray_count(self.tracer) - rays0
        rec.wall_ms = 1e3 * wall_s
        self.group.add_stage(name, place, self.clock.duration_s(wall_s, rec.rays, rec.pixels), after=after,
                             rays=rec.rays, pixels=rec.pixels, size_bytes=rec.bytes, wall_ms=rec.wall_ms)
        self.stages.append(rec)

    def modelled_stage(self, name: str, place: str, duration_ms: float, after=None) -> None:
        """A fixed-cost stage that is computed, not measured (e.g. a PCIe copy from bytes / bandwidth)."""
        if not (duration_ms >= 0 and math.isfinite(duration_ms)):
            raise ValueError(f"modelled stage '{name}': duration_ms must be finite and >= 0, got {duration_ms}")
        self.group.add_stage(name, place, duration_ms / 1e3, after=after, kind="modelled")
        self.stages.append(StageRecord(name, place))

    def send(self, name: str, payload, direction: str = "down", protocol: str | None = None,
             after=None) -> Message:
        """Sends ``payload`` (bytes, or a size in bytes) through the network; returns the delivery at once."""
        if isinstance(payload, (bytes, bytearray, memoryview)):
            data, size = bytes(payload), len(payload)
        else:
            data, size = None, int(payload)
        protocol = protocol or self.protocol
        ev, d = self.group.add_message(name, size, direction, protocol, after=after)
        msg = Message(name, size, direction, protocol, ev.start_s, float(d.arrival_s), int(d.delivered_bytes),
                      [tuple(r) for r in (getattr(d, "lost_ranges", None) or [])],
                      int(getattr(d, "retransmissions", 0)), ev.complete, data)
        self.messages.append(msg)
        return msg
