"""The method contract: the base class a pipeline subclasses, and the context it runs its stages in.

See ``docs/method-contract.md`` for the full contract (clients, stages, messages, information flow, work
counters, outputs, the simulated clock, config.toml).
"""
from __future__ import annotations

import copy
import math
import struct
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import greenlet
import numpy as np

from suite.harness.timeline import WORK_KINDS, Event, Group, SimulationError, deliver_bytes


class Method:
    """Base class of a split-rendering pipeline.

    Subclasses set ``name`` (= folder name) and ``mode`` and implement ``frame`` (sync) or ``server_update`` and
    ``client_frame`` (async, with ``client_input`` when the client sends more than its pose). The harness makes
    one instance for the server and one per client, so that what a client knows reaches the server only in
    messages, and the other way round.
    """

    name: str = ""
    mode: str = "sync"          # "sync" | "async"
    uses_network = True         # False: the zero-latency run would be identical, so the harness skips it
    # The light transport the method models: "direct" (emitters seen directly plus one bounce of direct lighting,
    # Mitsuba's `direct` integrator) or "global" (multi-bounce, Mitsuba's `path`). Runs are scored against both
    # references; the report takes the one named here as the method's own ground truth.
    light_transport: str = "direct"
    # Declared per-frame outputs (name -> description): ``ctx.record(name=value)`` in a client frame stores
    # them as ``info_<name>`` columns of frames.parquet; ``update_outputs`` the same for server updates
    # (updates.parquet). Recording an undeclared name is an error.
    outputs: dict = {}
    update_outputs: dict = {}
    # A method whose model shades every surface as Lambertian: the rest of the sentence :meth:`omissions` says of a
    # scene's non-diffuse materials ("are shaded as Lambertian with their albedo", with the model's reason). Empty:
    # the method follows the materials' BSDFs.
    flattens_materials: str = ""

    def __init__(self, params: dict):
        self.params = dict(params)
        self.prepared = None

    def prepare(self, scene, tracer):
        """Offline precomputation before the first frame (timed as prepare_ms); returns picklable data or None.

        The data is cached and shared by runs that differ only in network, protocol or client count; the
        harness hands it to every instance through :meth:`restore`. ``scene`` is the server's view: it has no
        camera poses (the server learns them from messages).
        """
        return None

    def omissions(self, scene) -> list[str]:
        """What of ``scene`` this method does not render, one sentence each (a light kind its model has no term for,
        say): the runner prints each as a warning and stores them as the run summary's ``omitted``, so that nothing
        of a scene is dropped silently. A method raises :class:`~suite.errors.UserError` instead where it would
        render nothing of the scene's light. The default: the scene's non-diffuse materials where the method
        declares :attr:`flattens_materials`, else nothing."""
        if not self.flattens_materials:
            return []
        odd, names = non_diffuse_materials(scene)
        return [f"its {odd} non-diffuse materials ({names}) {self.flattens_materials}"] if odd else []

    def restore(self, prepared) -> None:
        """Takes the output of :meth:`prepare` (fresh or from the cache)."""
        self.prepared = prepared

    def reset(self) -> None:
        """Clears per-sequence state; called before each frame sequence (the run, then its zero-latency run)."""

    def frame(self, ctx: "Context") -> np.ndarray:
        """Sync: one client frame; returns the displayed image, float32 (H, W, 3)."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'sync' but does not implement frame()")

    def client_input(self, ctx: "Context") -> None:
        """Async: what the client sends the server at the start of each frame; by default its pose."""
        ctx.send_pose()

    def server_update(self, ctx: "Context") -> None:
        """Async: one server update for ``ctx.client`` from what the server received (``ctx.inbox``); its
        results reach the client only as the bytes of the messages it sends."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'async' but does not implement server_update()")

    def client_frame(self, ctx: "Context", update: "Update | None") -> np.ndarray:
        """Async: one client frame with the newest arrived update (None before the first)."""
        raise NotImplementedError(f"{type(self).__name__} is mode 'async' but does not implement client_frame()")

    def __str__(self) -> str:
        args = ",".join(f"{k}={self.params[k]}" for k in sorted(self.params))
        return f"{self.name}({args})"


def non_diffuse_materials(scene, listed: int = 4) -> tuple[int, str]:
    """How many of the materials ``scene``'s faces use have a BSDF other than diffuse, and them named with their
    kinds (the first ``listed``), for a method's :meth:`Method.omissions` where its model shades every surface as
    Lambertian (:attr:`Method.flattens_materials`): ``(2, "'frame' (mirror), 'pane' (glass)")``; ``(0, "")`` for an all-diffuse scene."""
    used = sorted(set(np.unique(scene.face_material).tolist()))
    odd = [scene.materials[m] for m in used if scene.materials[m].shading_kind != "diffuse"]
    names = ", ".join(f"'{m.name}' ({m.shading_kind})" for m in odd[:listed])
    return len(odd), names + (", …" if len(odd) > listed else "")


@dataclass
class StageRecord:
    """Counters of one stage; the method may set ``pixels`` and ``bytes`` and add work inside the block."""

    name: str
    place: str
    pixels: int = 0
    bytes: int = 0
    rays: int = 0
    wall_ms: float = float("nan")
    work: dict = field(default_factory=dict)

    def count(self, **work) -> None:
        """Declares work that is not ray tracing: ``taps`` (filter taps: pixels x taps x passes), ``points``
        (point-cloud records or point-light pairs shaded), ``codec_bytes`` (bytes a codec read or wrote)."""
        for kind, n in work.items():
            if kind not in WORK_KINDS or kind == "pixels":
                raise ValueError(f"stage '{self.name}': unknown work counter '{kind}' "
                                 f"(choose from {', '.join(k for k in WORK_KINDS if k != 'pixels')})")
            if int(n) < 0:
                raise ValueError(f"stage '{self.name}': work counter '{kind}' must be >= 0, got {n}")
            self.work[kind] = self.work.get(kind, 0) + int(n)


@dataclass
class Clock:
    """Where stage durations come from: measured wall time, or a work model (machine-independent)."""

    source: str = "measured"        # "measured" | "work"
    work_ns_per_ray: float = 50.0
    work_ns_per_pixel: float = 20.0
    work_ns_per_tap: float = 2.0
    work_ns_per_point: float = 50.0
    work_ns_per_codec_byte: float = 5.0

    def duration_s(self, wall_s: float, rays: int, pixels: int, work: dict | None = None) -> float:
        if self.source == "work":
            work = work or {}
            return 1e-9 * (rays * self.work_ns_per_ray + pixels * self.work_ns_per_pixel
                           + work.get("taps", 0) * self.work_ns_per_tap
                           + work.get("points", 0) * self.work_ns_per_point
                           + work.get("codec_bytes", 0) * self.work_ns_per_codec_byte)
        return wall_s


def wait_for_device(tracer) -> None:
    """Waits for the device work a stage launched (a Dr.Jit tracer's: kernels run asynchronously on both variants,
    on the CPU's thread pool too), so that the stage's clock stops when its work is done, not when the next stage's
    first copy waits for it."""
    device = getattr(tracer, "device", None)
    if device is not None:
        device.sync()


def _ray_count(tracer) -> int:
    counters = getattr(tracer, "counters", None) or {}
    return int(counters.get("rays_intersect", 0)) + int(counters.get("rays_occluded", 0))


# ------------------------------------------------------------------------------------------ information flow

def current_place() -> str:
    """Where the code running now executes: "server" inside a server stage or a server update, else "client"."""
    return getattr(greenlet.getcurrent(), "sb_place", "client")


@contextmanager
def running_on(place: str):
    g = greenlet.getcurrent()
    before = getattr(g, "sb_place", "client")
    g.sb_place = place
    try:
        yield
    finally:
        g.sb_place = before


class ClientCamera:
    """A client's own camera path. Server code cannot read it: the server learns poses from messages."""

    def __init__(self, path, client: int):
        self._path = path
        self._client = client

    def pose_at(self, t_s: float):
        if current_place() == "server":
            raise SimulationError(f"server code read client {self._client}'s camera path; the server knows a "
                                  f"pose only from a message the client sent (ctx.receive_pose)")
        return self._path.pose_at(t_s)

    def __getattr__(self, name):
        if name in ("keys",) and current_place() == "server":
            raise SimulationError(f"server code read client {self._client}'s camera keys")
        return getattr(self._path, name)


class ServerCamera:
    """The server's knowledge of one client's camera: the shared configuration (field of view, resolution,
    frame rate) and the poses that arrived in messages, by scene time."""

    def __init__(self, path, client: int):
        self.fov_deg = path.fov_deg
        self.resolution = path.resolution
        self.fps = path.fps
        self._t0_s = path.frame_time_s(0)
        self._client = client
        self.poses: dict[float, object] = {}

    def frame_time_s(self, frame_index: int) -> float:
        return self._t0_s + frame_index / self.fps

    def add(self, t_s: float, pose) -> None:
        self.poses[float(t_s)] = pose

    def pose_at(self, t_s: float):
        pose = self.poses.get(float(t_s))
        if pose is None:
            raise SimulationError(f"the server has received no pose of client {self._client} for scene time "
                                  f"{t_s:.6f} s (poses reach it only in messages: ctx.receive_pose)")
        return pose


def scene_view(scene, camera):
    """The same scene with another camera (shallow: geometry, materials and lights are shared)."""
    view = copy.copy(scene)
    view.camera = camera
    return view


# Standard pose message (``ctx.send_pose``): scene time, then position, target and up as float64, then the
# field of view. Doubles keep the server's view bit-identical to the client's.
_POSE = struct.Struct("<d9dd")


def encode_pose(t_s: float, pose, fov_deg: float) -> bytes:
    return _POSE.pack(float(t_s), *np.asarray(pose.position, np.float64), *np.asarray(pose.target, np.float64),
                      *np.asarray(pose.up, np.float64), float(fov_deg))


def decode_pose(data: bytes):
    """(t_s, CameraPose, fov_deg) from a standard pose message; ValueError when it is truncated."""
    from suite.core.scene.model import CameraPose

    if data is None or len(data) < _POSE.size:
        raise ValueError(f"pose message of {0 if data is None else len(data)} bytes, expected {_POSE.size}")
    v = _POSE.unpack_from(data)
    p = np.asarray(v[1:10], np.float64).reshape(3, 3)
    return v[0], CameraPose(p[0], p[1], p[2]), v[10]


# ----------------------------------------------------------------------------------------------- messages

class Message:
    """A message as the method sees it. Size, direction and send time are known at once; the outcome
    (arrival, losses, delivered bytes) is read when the simulated clock has reached the arrival, so reading it
    outside a stage waits, and reading it inside a stage that does not depend on the message is an error."""

    def __init__(self, event: Event, ctx: "Context", payload: bytes | None):
        self.event = event
        self._ctx = ctx
        self._payload = payload
        self.name = event.name
        self.size_bytes = event.size_bytes
        self.direction = event.place
        self.protocol = event.protocol
        self.sent_s = event.start_s

    def _final(self) -> Event:
        tl = self._ctx.group.timeline
        if not tl.is_final(self.event):
            if self._ctx._in_stage is not None:
                raise SimulationError(f"stage '{self._ctx._in_stage}' reads message '{self.name}' before it "
                                      f"arrived; name it in the stage's after=[...]")
            tl.wait_final(self.event)
        return self.event

    @property
    def arrival_s(self) -> float:
        return float(self._final().delivery.arrival_s)

    @property
    def delivered_bytes(self) -> int:
        return self._final().delivered_bytes

    @property
    def lost_ranges(self) -> list:
        return self._final().lost_ranges

    @property
    def retransmissions(self) -> int:
        return self._final().retransmissions

    @property
    def complete(self) -> bool:
        return self._final().complete

    @property
    def data(self) -> bytes | None:
        """The bytes the receiver holds: the payload with every lost range zero-filled."""
        ev = self._final()
        return deliver_bytes(self._payload, ev.size_bytes, ev.lost_ranges)

    @property
    def transfer_ms(self) -> float:
        return 1e3 * (self._final().end_s - self.sent_s)


@dataclass
class Delivered:
    """A message that reached its receiver, as bytes (``data``: lost ranges zero-filled)."""

    name: str
    data: bytes | None
    size_bytes: int
    lost_ranges: list
    complete: bool
    sent_s: float
    arrival_s: float
    frame: int = -1          # for client input: the client frame that sent it
    frame_start_s: float = math.nan


@dataclass
class Update:
    """What an async client frame gets: the newest update that arrived, as the messages its server sent."""

    index: int
    input_t_s: float         # scene time of the client input the update was made from
    messages: dict           # name -> Delivered
    is_new: bool = False     # first client frame that uses this update

    def __getitem__(self, name: str) -> Delivered:
        return self.messages[name]


def delivered(event: Event, payload, frame: int = -1, frame_start_s: float = math.nan) -> Delivered:
    return Delivered(event.name, deliver_bytes(payload, event.size_bytes, event.lost_ranges), event.size_bytes,
                     event.lost_ranges, event.complete, event.start_s, event.end_s, frame, frame_start_s)


# ----------------------------------------------------------------------------------------------- context

class Context:
    """What a method sees during one frame or update of one client. See docs/method-contract.md."""

    def __init__(self, group: Group, *, scene, tracer, t_s: float, prev_t_s, resolution, seed: int,
                 params: dict, zero_latency: bool, protocol: str = "tcp", clock: Clock | None = None,
                 update_index: int = -1, update_t_s: float | None = None, update_is_new: bool = False,
                 client: int = 0, clients: int = 1, server_scene=None, inbox=None, outputs: dict | None = None,
                 payloads: dict | None = None):
        self.group = group
        self._client_scene = scene
        self._server_scene = server_scene if server_scene is not None else scene
        self.tracer = tracer
        self.t_s = t_s
        self.prev_t_s = prev_t_s
        self.resolution = tuple(resolution)
        self.loop = group.loop
        self.index = group.index
        self.client = int(client)
        self.clients = int(clients)
        self.params = params
        self.zero_latency = zero_latency
        self.protocol = protocol
        self.clock = clock or Clock()
        loop_id = 0 if group.loop == "frame" else 1
        # One independent stream per (run seed, loop, index, client): reruns and other frames do not shift it.
        # Client 0 keeps the three-part key, so single-client runs keep their images.
        key = [int(seed), loop_id, int(group.index)] + ([self.client] if self.client else [])
        self.seed = int(np.random.SeedSequence(key).generate_state(1)[0])
        self.rng = np.random.default_rng(self.seed)
        self.update_index = update_index
        self.update_t_s = update_t_s
        self.update_is_new = update_is_new
        self.inbox: list[Delivered] = list(inbox or [])
        self.stages: list[StageRecord] = []
        self.messages: list[Message] = []
        self._declared = outputs or {}
        self.outputs: dict = {}
        self._payloads = payloads if payloads is not None else {}
        self._in_stage: str | None = None

    # -- views

    @property
    def scene(self):
        """The scene as the code running now knows it: on the client, with this client's camera path; on the
        server (server stages and updates), with only the poses that arrived in messages."""
        return self._server_scene if current_place() == "server" else self._client_scene

    # -- stages

    @contextmanager
    def stage(self, name: str, place: str, after=None):
        """Runs the block as a stage on ``place``; times it and counts rays (tracer counter deltas).

        Messages the stage depends on are waited for before the block runs, so the block may read them.
        """
        for dep in self.group.dependencies(name, after):
            self.group.timeline.wait_final(self.group.events[dep])
        rec = StageRecord(name, place)
        rays0 = _ray_count(self.tracer)
        self._in_stage = name
        with running_on(place):
            t0 = time.perf_counter()
            yield rec
            wait_for_device(self.tracer)
            wall_s = time.perf_counter() - t0
        self._in_stage = None
        rec.rays = _ray_count(self.tracer) - rays0
        rec.wall_ms = 1e3 * wall_s
        work = dict(rec.work)
        self.group.add_stage(name, place, self.clock.duration_s(wall_s, rec.rays, rec.pixels, work), after=after,
                             rays=rec.rays, pixels=rec.pixels, size_bytes=rec.bytes, wall_ms=rec.wall_ms, work=work)
        self.stages.append(rec)

    def modelled_stage(self, name: str, place: str, duration_ms: float, after=None) -> None:
        """A fixed-cost stage that is computed, not measured (e.g. a PCIe copy from bytes / bandwidth)."""
        if not (duration_ms >= 0 and math.isfinite(duration_ms)):
            raise ValueError(f"modelled stage '{name}': duration_ms must be finite and >= 0, got {duration_ms}")
        self.group.add_stage(name, place, duration_ms / 1e3, after=after, kind="modelled")
        self.stages.append(StageRecord(name, place))

    # -- messages

    def send(self, name: str, payload, direction: str = "down", protocol: str | None = None,
             after=None) -> Message:
        """Sends ``payload`` (bytes, or a size in bytes) between this client and the server."""
        if isinstance(payload, (bytes, bytearray, memoryview)):
            data, size = bytes(payload), len(payload)
        else:
            data, size = None, int(payload)
        ev, _ = self.group.add_message(name, size, direction, protocol or self.protocol, after=after)
        self._payloads[ev.seq] = data
        msg = Message(ev, self, data)
        self.messages.append(msg)
        return msg

    def send_pose(self, name: str = "pose", protocol: str = "tcp", after=()) -> Message:
        """Client: sends this frame's camera pose to the server (the standard pose message). Poses travel over
        TCP by default: a lost pose would leave the server without the client's view."""
        cam = self._client_scene.camera
        return self.send(name, encode_pose(self.t_s, cam.pose_at(self.t_s), cam.fov_deg), direction="up",
                         protocol=protocol, after=list(after))

    def receive_pose(self, message):
        """Server: decodes a standard pose message (a Message or a Delivered) and makes the pose known to the
        server's camera view; returns (t_s, pose)."""
        data = message.data
        t_s, pose, _ = decode_pose(data)
        self._server_scene.camera.add(t_s, pose)
        return t_s, pose

    def latest_pose(self, name: str = "pose"):
        """Server update: the newest standard pose message in the inbox, decoded and made known; (t_s, pose)."""
        for m in reversed(self.inbox):
            if m.name == name and m.complete:
                return self.receive_pose(m)
        raise SimulationError(f"update {self.index} of client {self.client}: no complete '{name}' message arrived")

    # -- outputs

    def record(self, **values) -> None:
        """Stores declared per-frame (or per-update) outputs; see ``Method.outputs``."""
        for key, value in values.items():
            if key not in self._declared:
                raise SimulationError(f"output '{key}' is not declared in the method's "
                                      f"{'update_outputs' if self.loop == 'update' else 'outputs'}")
            self.outputs[key] = value
