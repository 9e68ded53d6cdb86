"""The Dr.Jit side of a Mitsuba tracer: device-resident scene tables, ray queries and explicit host copies.

``tracer.device`` (a :class:`Device`) exists for the vectorised Mitsuba variants (``llvm_ad_rgb``, ``cuda_ad_rgb``;
None for Embree and ``scalar_rgb``). Everything here works on Dr.Jit arrays of the tracer's variant and stays on the
device: on ``llvm_ad_rgb`` the kernels are vectorised and multi-threaded on the CPU, on ``cuda_ad_rgb`` they run on
the GPU. The types are taken from the variant's own module, so a process that switches Mitsuba's active variant in
between (a loader, a reference render) cannot mix them.

Host memory is reached only through :meth:`Device.to_host` and :meth:`Device.to_device`, which count the bytes they
move (``device.counters``), so a method can model them as stages with their bytes.

Ray queries (:meth:`Device.closest`, :meth:`Device.occluded_rays`) take rays in the tracing frame (float32 origins
minus ``tracer.shift``) and build lazily evaluated Dr.Jit expressions, so ray generation, traversal and what
follows fuse into one kernel. They resolve the global face index from the hit shape's registry id (never
``shape_index``, which is 0 on ``cuda_ad_rgb`` whatever the shape) and apply the alpha test exactly as the host
path does (:mod:`suite.core.trace.alpha`), in float64 where it does.
"""
from __future__ import annotations

import contextlib
import gc
import sys
import threading
from dataclasses import dataclass

import numpy as np

from suite.core.trace.alpha import ALPHA_STEP_ULPS, MAX_ALPHA_LAYERS
from suite.core.trace.base import ALPHA_BOX_PAD, MAX_RAY_LENGTH
from suite.core.trace.robust import FLOAT_SCALE, OFFSET_ULPS

TWO_M23 = 1.1920928955078125e-07  # 2**-23: a float32 ULP at exponent 0
# Recordings kept per frozen function (one per resolution and set of fields); the least recently used goes first.
FROZEN_RECORDINGS = 16
ALIGN_BYTES = 64  # the alignment of host buffers handed to Dr.Jit (see _aligned)


def _aligned(a: np.ndarray) -> np.ndarray:
    """``a`` contiguous and at a 64-byte aligned address (copied only where it is not). Dr.Jit's LLVM backend maps
    numpy memory and tells aligned from unaligned buffers; a recorded kernel (:meth:`Device.frozen`) records again
    when that status of an input changes, which numpy's 16-byte alignment made happen at random frames."""
    a = np.ascontiguousarray(a)
    if a.ctypes.data % ALIGN_BYTES == 0 or a.nbytes == 0:
        return a
    buf = np.empty(a.nbytes + ALIGN_BYTES, np.uint8)
    start = (-buf.ctypes.data) % ALIGN_BYTES
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


@dataclass
class HostCopy:
    """What :meth:`Device.to_host` returns when asked for the byte count too."""

    array: np.ndarray
    nbytes: int


class Device:
    """Device-resident data and queries of one :class:`~suite.core.trace.mitsuba_backend.MitsubaTracer`."""

    def __init__(self, tracer):
        import drjit as dr

        self.tracer = tracer
        self.scene = tracer.scene
        self.variant = tracer.variant
        self.m = sys.modules[f"mitsuba.{self.variant}"]  # this variant's types, whatever variant is active
        self.dr = dr
        self.is_cuda = self.variant.startswith("cuda")
        self.name = "cuda" if self.is_cuda else "llvm"
        m = self.m
        self.Float, self.Float64, self.UInt32, self.Int32, self.Bool = m.Float, m.Float64, m.UInt32, m.Int32, m.Bool
        self.Point3f, self.Point3d, self.Vector3f, self.Vector3d = m.Point3f, m.Point3d, m.Vector3f, m.Vector3d
        self.Point2f, self.Vector2f = m.Point2f, m.Vector2f
        self.counters = {"bytes_to_host": 0, "bytes_to_device": 0, "copies_to_host": 0, "copies_to_device": 0}
        self._tables: SceneTables | None = None
        self._zero = None  # UInt32 0 in memory (see opaques)
        self._frozen = {}  # name -> the recorded kernels of a frozen function (see frozen)
        self.record_kernels = True  # False: frozen() runs its function afresh every call (tests, debugging)
        self._frozen_lock = threading.RLock()  # one recorded call at a time (a recording rebinds attributes)
        self._shift = [float(x) for x in tracer.shift]

    # ------------------------------------------------------------------------------------------ basics
    def opaque(self, dtype, value):
        """A scalar the kernels read from memory (so a new value never compiles a new kernel)."""
        return self.dr.opaque(dtype, value)

    def opaques(self, values) -> list:
        """Float64 scalars the kernels read from memory, as :meth:`opaque` makes them (no recompilation when a value
        changes), one size-1 array per value. On cuda_ad_rgb each :meth:`opaque` is a launch of its own (a fill of one
        element; a G-buffer needs about 40 per frame), so there the values travel in one host-to-device copy and each
        is a load from it at an index read from memory (a gather at a literal index would again be a copy launch of
        its own). On llvm_ad_rgb a fill costs nothing worth saving, while a per-lane load of float64 costs an AVX2
        gather per packet (the 1080p G-buffer 166 ms instead of 138 ms): there they stay broadcast scalars.
        Converting an element to Float32 rounds as :meth:`opaque` of that type would."""
        dr, F64 = self.dr, self.Float64
        if not self.is_cuda:
            return [dr.opaque(F64, float(x)) for x in values]
        block = self.to_device(np.asarray(values, np.float64).reshape(-1), F64)
        zero = self._zero_index()
        return [dr.gather(F64, block, zero + k) for k in range(len(values))]

    def _zero_index(self):
        """UInt32 0 in memory, made once (the index :meth:`opaques` reads its block at, on cuda_ad_rgb)."""
        if self._zero is None:
            self._zero = self.dr.opaque(self.UInt32, 0)
        return self._zero

    # The arrays kernels read through the device (owner, attributes): what a recording must take as its inputs.
    _KERNEL_ARRAYS = (("tables", ("vpos", "vnrm", "vuv", "faces", "face_material", "face_object", "albedo", "emission",
                                  "kind", "threshold", "face_tested")),
                      ("tables.albedo_tex", ("offset", "width", "height", "stored", "data")),
                      ("tables.opacity_tex", ("offset", "width", "height", "stored", "data")),
                      ("tracer", ("_face_table", "_first_face_by_id")),
                      ("device", ("_zero",)),
                      ("opaque_group", ("face_table",)),
                      ("alpha_group", ("face_table",)))

    def _groups(self) -> tuple:
        """The tracer's (opaque, alpha-tested) sub-scenes where the device's shadow rays use them, else ()."""
        if self.tracer._alpha is None or self.is_cuda:
            return ()
        return self.tracer._alpha_groups() or ()

    def _owner(self, name: str):
        root = name.split(".")[0]
        if root in ("opaque_group", "alpha_group"):
            obj = self._groups()[0 if root == "opaque_group" else 1]
        else:
            obj = {"tables": self.tables, "tracer": self.tracer, "device": self}[root]
        for part in name.split(".")[1:]:
            obj = getattr(obj, part)
        return obj

    def kernel_state(self, shadow_rays: bool = False) -> dict:
        """The device arrays kernels read through this device (scene tables, the tracer's id tables) and the scenes
        they trace, as one PyTree: the inputs a recorded kernel (:meth:`frozen`) is replayed on. ``shadow_rays``:
        with the opaque and alpha-tested sub-scenes shadow rays query (built on first use, and again after animated
        objects moved, so kernels that trace no shadow rays leave them alone)."""
        if self.is_cuda:
            self._zero_index()  # present from the first recording on: the inputs keep one structure
        arrays = {}
        groups = self._groups() if shadow_rays else ()
        for owner, attrs in self._KERNEL_ARRAYS:
            if owner.endswith("_group") and not groups:
                continue
            obj = self._owner(owner)
            for attr in attrs:
                value = getattr(obj, attr, None)
                if value is not None:
                    arrays[f"{owner}:{attr}"] = value
        scenes = [self.tracer.query_scene] + [grp.mscene for grp in groups if grp.mscene is not None]
        return {"arrays": arrays, "scenes": scenes}

    @contextlib.contextmanager
    def _bound(self, arrays: dict):
        """Points the owners' attributes at ``arrays`` (a recording's input variables) for the duration."""
        saved = []
        try:
            for key, value in arrays.items():
                owner, attr = key.split(":")
                obj = self._owner(owner)
                saved.append((obj, attr, getattr(obj, attr)))
                setattr(obj, attr, value)
            yield
        finally:
            for obj, attr, value in reversed(saved):
                setattr(obj, attr, value)

    def frozen(self, name: str, fn, shadow_rays: bool = False):
        """``fn`` recorded on its first call and replayed afterwards (Dr.Jit's ``dr.freeze``): a replay launches the
        recorded kernels on the new inputs without tracing any Python, which on a GPU costs as much as the work of
        a 1080p G-buffer. ``fn``'s Dr.Jit arguments are its inputs; its plain Python arguments select a recording
        (one per resolution, say); the arrays it reads through this device (:meth:`kernel_state`) are handed in
        too, bound to the device's attributes while it is recorded (so recorded calls on one device take turns, and
        no other thread should trace kernels on it meanwhile). A tracer whose queries go to something other than a
        Mitsuba scene (a test's wrapper) runs ``fn`` directly. ``shadow_rays``: ``fn`` traces shadow rays
        (:meth:`kernel_state`)."""
        dr = self.dr
        if not self.record_kernels or not isinstance(self.tracer.query_scene, self.m.Scene):
            return fn
        rec = self._frozen.get(name)
        if rec is None:
            def run(state, *args):  # runs while recording only
                # No garbage collection meanwhile: freeing an array that an earlier, unrelated computation left to
                # the collector can enqueue a host function on the device, which a recording cannot hold (Dr.Jit
                # then aborts the process).
                enabled = gc.isenabled()
                gc.disable()
                try:
                    with self._bound(state["arrays"]):
                        return fn(*args)
                finally:
                    if enabled:
                        gc.enable()

            rec = self._frozen[name] = dr.freeze(run, limit=FROZEN_RECORDINGS, warn_after=FROZEN_RECORDINGS + 1)

        def call(*args):
            with self._frozen_lock:
                return rec(self.kernel_state(shadow_rays), *args)

        return call

    @property
    def copied_bytes(self) -> int:
        """Bytes copied between host and device memory so far, both ways (``counters``)."""
        return int(self.counters["bytes_to_device"] + self.counters["bytes_to_host"])

    def arange(self, n: int):
        return self.dr.arange(self.UInt32, int(n))

    def sync(self) -> None:
        """Waits for the device (kernels launch asynchronously on both backends)."""
        self.dr.sync_thread()

    def kernel_ms(self, fn, repeats: int = 5) -> float:
        """Median over ``repeats`` calls of ``fn`` (after one warm-up) of the summed execution time of the device work
        each call launched (Dr.Jit's kernel history: kernels, memsets, reductions): device time without the host's
        per-call costs (tracing the kernel in Python, code generation and cache lookup, launch), which the wall time
        of a call also holds. Kept apart from wall-time measurements: recording the history times every launch."""
        dr = self.dr
        fn()
        was = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            per_call = []
            for _ in range(max(int(repeats), 1)):
                dr.sync_thread()
                dr.kernel_history()  # drops what earlier work left in the history
                fn()
                dr.sync_thread()
                per_call.append(sum(float(h.get("execution_time", 0.0)) for h in dr.kernel_history()))
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, was)
        return float(np.median(per_call))

    def eval(self, *values) -> None:
        """Evaluates ``values`` (one fused kernel where their sizes agree) and waits for them."""
        self.dr.eval(*values)
        self.dr.sync_thread()

    def to_host(self, value, dtype=None, with_bytes: bool = False):
        """Copies a Dr.Jit array to a numpy array (vectors of width 3 or 2 come back as (N, 3) / (N, 2) rows) and
        counts the bytes. The one place device data becomes host memory (:meth:`to_host_all` for several)."""
        return self.to_host_all([value], [dtype], with_bytes)[0]

    def to_host_all(self, values, dtypes=None, with_bytes: bool = False, keep=()) -> list:
        """:meth:`to_host` of several arrays, evaluated together first: arrays of one size in one kernel, where a
        :meth:`to_host` each launches a kernel each for their gathers and interleaving. ``keep``: arrays that stay on
        the device, evaluated in the same kernel (a lazy value both copied and kept would be computed twice)."""
        dr = self.dr
        if not values:
            return []
        dtypes = [None] * len(values) if dtypes is None else dtypes
        # Vectors are interleaved on the device (x0 y0 z0 x1 ...) into a private buffer: on llvm_ad_rgb numpy then
        # views it (no second copy; the array keeps the buffer alive), on cuda_ad_rgb it is one device-to-host copy.
        flat = [self.interleaved(v) if dr.depth_v(v) > 1 else v for v in values]
        dr.eval(*flat, *keep)
        out = []
        for v, f, dtype in zip(values, flat, dtypes):
            if dr.depth_v(v) > 1:
                a = np.asarray(f.numpy()).reshape(-1, len(v))
            else:
                a = np.array(f.numpy())  # a copy: the device array may change later (scatters)
            out.append(self._counted(a, dtype, with_bytes))
        return out

    def _counted(self, a: np.ndarray, dtype, with_bytes: bool):
        """A host copy counted (its bytes as they crossed, before any conversion on the host), converted to
        ``dtype``."""
        nbytes = int(a.nbytes)
        if dtype is not None and a.dtype != np.dtype(dtype):
            a = a.astype(dtype)
        self.counters["bytes_to_host"] += nbytes
        self.counters["copies_to_host"] += 1
        return HostCopy(a, nbytes) if with_bytes else a

    def interleaved(self, value):
        """A vector's components interleaved into one flat array (x0 y0 z0 x1 ...), lazily: written by the kernel that
        computes the vector, in :meth:`to_host_all`'s layout, where :meth:`to_host_all` would interleave them in a
        kernel of its own (reading and writing every value once more). :meth:`rows_to_host` brings it back."""
        return self.dr.ravel(value, order="F")

    def rows_to_host(self, flat, width: int, dtype=None):
        """An :meth:`interleaved` vector of ``width`` components as (N, width) host rows, counted as :meth:`to_host`
        counts: on ``llvm_ad_rgb`` a view of its buffer (the array keeps the buffer alive; nothing writes to an
        interleaved copy later), on ``cuda_ad_rgb`` one device-to-host copy."""
        self.dr.eval(flat)
        return self._counted(np.asarray(flat.numpy()).reshape(-1, int(width)), dtype, False)

    def to_device(self, array: np.ndarray, dtype):
        """Uploads a numpy array as Dr.Jit ``dtype`` (for vector types, (N, k) rows) and counts the bytes."""
        a = np.asarray(array)
        if a.ndim == 2:
            value = dtype(*[_aligned(a[:, c]) for c in range(a.shape[1])])
        else:
            value = dtype(_aligned(a))
        self.counters["bytes_to_device"] += int(a.nbytes)
        self.counters["copies_to_device"] += 1
        return value

    # ------------------------------------------------------------------------------------------ tables
    @property
    def tables(self) -> "SceneTables":
        if self._tables is None:
            self._tables = SceneTables(self)
        return self._tables

    def on_update(self, positions_world: np.ndarray, t_s: float) -> None:
        """Called by the tracer after it moved animated objects: updates the moving vertices' attributes."""
        if self._tables is not None:
            self._tables.update(positions_world, t_s)

    # ------------------------------------------------------------------------------------------ numerics
    def ulp32(self, x64):
        """``np.spacing(np.float32(x))`` as float64 for x >= 0 (0 below the normal range, where the callers' absolute
        floors take over)."""
        dr = self.dr
        bits = dr.reinterpret_array(self.UInt32, self.Float(x64)) & 0x7F800000
        return self.Float64(dr.reinterpret_array(self.Float, bits)) * TWO_M23

    def local_f32(self, p64):
        """float64 world points → float32 tracing-frame points (minus ``tracer.shift``), rounded once."""
        s = self._shift
        return self.Point3f(self.Float(p64.x - s[0]), self.Float(p64.y - s[1]), self.Float(p64.z - s[2]))

    def offset_origin(self, p64, n64):
        """:func:`suite.core.trace.robust.offset_ray_origin` on the device, operation for operation (float64 world
        points and unit normals; returns float64 world points)."""
        dr, s = self.dr, self._shift
        m = dr.maximum(dr.maximum(dr.abs(p64.x - s[0]), dr.abs(p64.y - s[1])), dr.abs(p64.z - s[2]))
        step = dr.maximum(OFFSET_ULPS * self.ulp32(m), FLOAT_SCALE)
        return self.Point3d(p64.x + step * n64.x, p64.y + step * n64.y, p64.z + step * n64.z)

    # ------------------------------------------------------------------------------------------ queries
    def ray(self, o_local, d, length):
        ray = self.m.Ray3f(o_local, d)
        ray.maxt = length
        return ray

    def global_prim(self, pi, valid):
        """Global face index of preliminary intersections (-1 on a miss)."""
        dr, t = self.dr, self.tracer
        if t._identity_prims:
            prim = self.Int32(pi.prim_index)
        else:
            slot = dr.reinterpret_array(self.UInt32, pi.shape)  # the shape's registry id, on every variant
            first = dr.gather(self.UInt32, t._first_face_by_id, slot, valid)
            prim = dr.gather(self.Int32, t._face_table, first + pi.prim_index, valid)
        return dr.select(valid, prim, -1)

    def closest_backend(self, o_local, d, length, active=True, group=None):
        """One backend closest-hit query: (t, prim, u, v) with misses normalised (inf, -1, 0, 0). ``group``: a
        :class:`~suite.core.trace.mitsuba_backend.MitsubaGroup` to query instead of the whole scene."""
        dr = self.dr
        scene = self.tracer.query_scene if group is None else group.mscene
        pi = scene.ray_intersect_preliminary(self.ray(o_local, d, length), coherent=False, active=active)
        valid = pi.is_valid() & active
        t = dr.select(valid, pi.t, dr.inf)
        u = dr.select(valid, pi.prim_uv.x, 0.0)
        v = dr.select(valid, pi.prim_uv.y, 0.0)
        if group is None:
            prim = self.global_prim(pi, valid)
        else:
            prim = dr.select(valid, dr.gather(self.Int32, group.face_table, pi.prim_index, valid), -1)
        return t, prim, u, v

    def closest(self, o_local, d, length, active=True):
        """Closest opaque hit of tracing-frame rays: ``(t, prim, u, v, traced)``, lazily. ``traced`` counts the backend
        queries per lane (1, plus one per transparent layer re-traced) or is None when nothing can be re-traced."""
        t, prim, u, v = self.closest_backend(o_local, d, length, active)
        if self.tracer._alpha is None:
            return t, prim, u, v, None
        return self._skip_transparent(o_local, d, length, t, prim, u, v, active)

    def _skip_transparent(self, o_local, d, length, t, prim, u, v, active, group=None):
        """:meth:`suite.core.trace.base.Tracer._skip_transparent` on the device, in the same float64 steps.

        The loop runs for lanes whose hit lies on an alpha-tested face (``pending``, one table lookup); its body first
        looks up the opacity there, so the texture work is done only in the (rare) packets that hit such a face, not
        masked in every packet. ``layers`` counts re-traces, as the host loop's iterations do. ``group``: re-trace
        against that sub-scene (the alpha-tested faces) instead of the whole scene."""
        dr, F, F64, U = self.dr, self.Float, self.Float64, self.UInt32
        tables = self.tables
        pending = tables.tested_face(prim, active)
        traced = dr.select(active, U(1), U(0))
        layers = dr.zeros(U, dr.width(t))
        o64 = self.Point3d(o_local)
        d64 = self.Vector3d(d)
        length64 = F64(length)

        def cond(t, prim, u, v, pending, layers, traced):
            return pending & (layers < MAX_ALPHA_LAYERS)

        def body(t, prim, u, v, pending, layers, traced):
            todo = tables.transparent(prim, u, v, pending)  # an opaque hit ends the lane's walk
            t64 = F64(t)
            p = dr.maximum(dr.maximum(dr.abs(o64.x + d64.x * t64), dr.abs(o64.y + d64.y * t64)),
                           dr.abs(o64.z + d64.z * t64))
            scale = dr.maximum(p, dr.abs(t64))
            start = t64 + dr.maximum(ALPHA_STEP_ULPS * self.ulp32(scale), FLOAT_SCALE)
            remaining = length64 - start
            gone = todo & (remaining <= 0.0)
            go = todo & ~gone
            o_next = self.Point3f(F(o64.x + d64.x * start), F(o64.y + d64.y * start), F(o64.z + d64.z * start))
            t2, p2, u2, v2 = self.closest_backend(o_next, d, F(remaining), go, group)
            t = dr.select(go, dr.select(p2 >= 0, F(start + F64(t2)), dr.inf), dr.select(gone, dr.inf, t))
            prim = dr.select(go, p2, dr.select(gone, -1, prim))
            u = dr.select(go, u2, dr.select(gone, 0.0, u))
            v = dr.select(go, v2, dr.select(gone, 0.0, v))
            traced = traced + dr.select(go, U(1), U(0))
            layers = layers + dr.select(go, U(1), U(0))
            pending = go & tables.tested_face(p2, go)
            return t, prim, u, v, pending, layers, traced

        t, prim, u, v, pending, layers, traced = dr.while_loop((t, prim, u, v, pending, layers, traced), cond, body)
        return t, prim, u, v, traced

    def occluded_rays(self, o_local, d, length, active=True):
        """Shadow-ray query of tracing-frame rays: ``(blocked, closest_traced)``, lazily. With alpha-tested materials,
        as the host's :meth:`~suite.core.trace.base.Tracer._occluded_split`: an any-hit query against the opaque
        faces, and the open rays that cross the alpha-tested faces' box walk those faces (closest hit, alpha test,
        re-trace past transparent texels; :meth:`_skip_transparent`); ``closest_traced`` counts those closest-hit
        queries per lane (None without alpha)."""
        tracer = self.tracer
        if tracer._alpha is None:
            blocked = tracer.query_scene.ray_test(self.ray(o_local, d, length), coherent=False, active=active) & active
            return blocked, None
        # OptiX binds one shader binding table (one scene) per kernel: on cuda_ad_rgb a kernel that traced the opaque
        # and the alpha-tested sub-scenes would have its second query disabled by Dr.Jit ("more than one OptiX shader
        # binding table was used within a single kernel") and its rays reported unblocked. The pass is one kernel
        # (a symbolic loop over lights on the GPU, where no evaluation can split it), so there shadow rays take the
        # whole-scene walk: the same answer, with a closest-hit walk for every ray the any-hit query found blocked.
        groups = None if self.is_cuda else tracer._alpha_groups()
        if groups is None:  # the whole-scene walk of the rays the any-hit query found blocked
            blocked = tracer.query_scene.ray_test(self.ray(o_local, d, length), coherent=False, active=active) & active
            _, prim, _, _, traced = self.closest(o_local, d, length, blocked)
            return blocked & (prim >= 0), traced
        opaque, alpha = groups
        dr = self.dr
        ray = self.ray(o_local, d, length)
        if alpha.mscene is None:  # no face uses the alpha-tested materials
            hit = tracer.query_scene.ray_test(ray, coherent=False, active=active) & active
            return hit, dr.zeros(self.UInt32, dr.width(d))
        by_opaque = dr.zeros(self.Bool, dr.width(d)) if opaque.mscene is None else \
            opaque.mscene.ray_test(ray, coherent=False, active=active) & active
        walk = active & ~by_opaque & self.crosses_box(o_local, d, length, alpha.box)

        def walk_alpha(walk):
            t, prim, u, v = self.closest_backend(o_local, d, length, walk, alpha)
            _, prim, _, _, traced = self._skip_transparent(o_local, d, length, t, prim, u, v, walk, alpha)
            return walk & (prim >= 0), traced

        n = dr.width(d)
        by_alpha, traced = self.where_any(walk, walk_alpha, dr.zeros(self.Bool, n), dr.zeros(self.UInt32, n))
        return by_opaque | by_alpha, traced

    def where_any(self, mask, fn, *otherwise):
        """``fn(mask)``'s values (a tuple) in the lanes of ``mask`` and ``otherwise`` elsewhere, with ``fn`` run only in
        the packets that have a lane in ``mask``: a symbolic loop of at most one iteration, whose condition a packet
        without such a lane fails at once. On ``llvm_ad_rgb`` a backend query costs a call per packet (SIMD group of
        lanes) even with every lane masked off; inside a kernel over all lanes this skips those calls for a query that
        few lanes make (the alpha-tested faces' walk of the shadow rays that cross their box)."""
        dr = self.dr

        def body(todo, *values):
            return (dr.zeros(self.Bool, dr.width(todo)), *fn(todo))

        _, *out = dr.while_loop((self.Bool(mask), *otherwise), lambda todo, *values: todo, body)
        return tuple(out)

    def crosses_box(self, o_local, d, length, box):
        """Bool: the segments o + t d, 0 <= t <= length (padded), cross ``box`` ((2, 3) float64 [lo, hi], padded): the
        slab test of :func:`suite.core.trace.base.box_candidates` in float32 with reciprocal directions (a filter
        only: the box's padding is far above float32 rounding, so no segment that meets a face inside is lost)."""
        dr, F = self.dr, self.Float
        t0 = dr.zeros(F, dr.width(d))
        t1 = F(length) * (1.0 + ALPHA_BOX_PAD) + 1e-6
        ok = self.Bool(True)
        for c in range(3):
            oc, dc = F(o_local[c]), F(d[c])
            lo, hi = float(box[0][c]), float(box[1][c])
            flat = dc == 0.0
            inv = dr.rcp(dr.select(flat, 1.0, dc))
            a, b = (lo - oc) * inv, (hi - oc) * inv
            t0 = dr.select(flat, t0, dr.maximum(t0, dr.minimum(a, b)))
            t1 = dr.select(flat, t1, dr.minimum(t1, dr.maximum(a, b)))
            ok = ok & (~flat | ((oc >= lo) & (oc <= hi)))
        return ok & (t0 <= t1)

    # ------------------------------------------------------------------------------------------ public, evaluated
    def _rays_in_frame(self, o, d, tmin, tmax):
        """World origins (Point3d or Point3f), unit directions and tmin/tmax (scalars or arrays) → tracing-frame
        float32 origins advanced by tmin, and lengths clipped to [0, MAX_RAY_LENGTH] (the numpy path's rules)."""
        dr, F = self.dr, self.Float
        o64 = self.Point3d(o)
        d = self.Vector3f(d)
        tmin_is_zero = isinstance(tmin, (int, float)) and tmin == 0.0
        o_local = self.local_f32(o64)
        if not tmin_is_zero:
            tmin_f = F(tmin)
            o_local = o_local + d * tmin_f
        else:
            tmin_f = F(0.0)
        if isinstance(tmax, (int, float)):
            if np.isinf(tmax) and tmin_is_zero:
                length = dr.full(F, float(MAX_RAY_LENGTH), dr.width(d))
            else:
                length = dr.clip(F(min(float(tmax), 3.0e38)) - tmin_f, 0.0, float(MAX_RAY_LENGTH))
        else:
            length = dr.clip(F(tmax) - tmin_f, 0.0, float(MAX_RAY_LENGTH))
        return o_local, d, length, tmin_f, tmin_is_zero

    def _query(self, name: str, kernel, shadow_rays: bool):
        """:meth:`occluded`'s or :meth:`intersect`'s kernel function: recorded and replayed (:meth:`frozen`) where the
        scene has alpha-tested materials. Their walk's symbolic loops and texture lookups make a graph whose tracing
        in Python costs about half a millisecond a call, more than a replay's bookkeeping (a tenth of one, which is
        more than tracing the few operations of a query without the walk)."""
        return kernel if self.tracer._alpha is None else self.frozen(name, kernel, shadow_rays)

    def occluded(self, o, d, tmin=0.0, tmax=np.inf):
        """Device-resident ``occluded``: world-space Dr.Jit rays in, evaluated Dr.Jit Bool out (counted)."""
        blocked, traced = self._query("occluded", _occluded_kernel, True)(self, o, d, tmin, tmax)
        self.dr.sync_thread()  # evaluated and waited for, as raw_occluded
        self.tracer.counters["rays_occluded"] += self.dr.width(blocked)
        if traced is not None:
            self.tracer.counters["rays_intersect"] += self.sum_u32(traced, MAX_ALPHA_LAYERS + 1)
        return blocked

    def intersect(self, o, d, tmin=0.0, tmax=np.inf):
        """Device-resident ``intersect``: world-space Dr.Jit rays in, evaluated ``DeviceHits`` out (counted)."""
        t, prim, u, v, traced = self._query("intersect", _intersect_kernel, False)(self, o, d, tmin, tmax)
        self.dr.sync_thread()
        n = self.dr.width(t)
        self.tracer.counters["rays_intersect"] += n if traced is None else self.sum_u32(traced, MAX_ALPHA_LAYERS + 1)
        return DeviceHits(t, prim, u, v)

    def sum_u32(self, counts, bound: int | None = None) -> int:
        """Sum of a per-lane UInt32 counter (a reduction; a few bytes come back to the host). ``bound``: an upper bound
        of every lane's value; where lanes x bound stays below 2**32 the sum runs in UInt32 (several times faster than
        through Float64, which is exact to 2**53 and serves otherwise)."""
        dr = self.dr
        n = dr.width(counts)
        if n == 0:
            return 0
        if bound is not None and n * int(bound) < 2 ** 32:
            return int(dr.sum(counts)[0])
        return int(dr.sum(self.Float64(counts))[0])

    # raw backend entry points on device-resident rays (the benchmarks' baseline)
    def raw_ray(self, o_local, d, length):
        ray = self.ray(self.Point3f(o_local), self.Vector3f(d), self.Float(length))
        self.dr.eval(ray)
        return ray

    def compacted_ray(self, active, o_local, d, length):
        """The tracing-frame rays of the lanes where ``active`` holds, gathered into an evaluated ``Ray3f``: the very
        rays a masked query traced, for a raw replay (:func:`suite.core.trace.recording.device_replay`)."""
        dr = self.dr
        idx = dr.compress(self.Bool(active))
        return self.raw_ray(dr.gather(self.Point3f, o_local, idx), dr.gather(self.Vector3f, d, idx),
                            dr.gather(self.Float, length, idx))

    def raw_occluded(self, ray):
        out = self.tracer.mscene.ray_test(ray, coherent=False)
        self.eval(out)
        return out

    def raw_intersect(self, ray):
        pi = self.tracer.mscene.ray_intersect_preliminary(ray, coherent=False)
        self.eval(pi.t, pi.prim_index, pi.prim_uv, pi.shape)
        return pi


def _occluded_kernel(dev, o, d, tmin, tmax):
    """:meth:`Device.occluded`'s kernel: (blocked, closest-hit queries per lane or None), evaluated."""
    o_local, d, length, _, _ = dev._rays_in_frame(o, d, tmin, tmax)
    blocked, traced = dev.occluded_rays(o_local, d, length)
    dev.dr.eval(blocked) if traced is None else dev.dr.eval(blocked, traced)
    return blocked, traced


def _intersect_kernel(dev, o, d, tmin, tmax):
    """:meth:`Device.intersect`'s kernel: (t, prim, u, v, backend queries per lane or None), evaluated."""
    o_local, d, length, tmin_f, tmin_is_zero = dev._rays_in_frame(o, d, tmin, tmax)
    t, prim, u, v, traced = dev.closest(o_local, d, length)
    if not tmin_is_zero:
        t = t + tmin_f
    dev.dr.eval(t, prim, u, v) if traced is None else dev.dr.eval(t, prim, u, v, traced)
    return t, prim, u, v, traced


@dataclass
class DeviceHits:
    t: object  # Float, inf on miss
    prim: object  # Int32, -1 on miss
    u: object  # Float
    v: object  # Float


ROW = 4  # values per vertex position, normal and face row on the device (a power of two: one packet gather)


def packet_rows(columns, dtype, width: int, min_rows: int = 0) -> np.ndarray:
    """``columns`` ((N,) or (N, k) arrays) side by side as a flat ``dtype`` table of rows of ``width`` values,
    zero-padded, with at least ``min_rows`` rows (a gather needs a non-empty source): the layout one packet gather
    (``dr.gather`` of a power-of-two row) reads a row of in a few vector loads."""
    cols = [np.asarray(c) for c in columns]
    cols = [c[:, None] if c.ndim == 1 else c for c in cols]
    n = len(cols[0])
    out = np.zeros((max(n, min_rows), width), dtype)
    at = 0
    for c in cols:
        out[:n, at:at + c.shape[1]] = c
        at += c.shape[1]
    return out.reshape(-1)


def float_rows(dev, *columns):
    """Float arrays of one size side by side as a flat Float table of rows of ``len(columns)`` values (a power of
    two), made on the device: :func:`packet_rows`' layout for values already there (one packet scatter)."""
    dr = dev.dr
    n = dr.width(columns[0])
    out = dr.zeros(dev.Float, len(columns) * n)
    dr.scatter(out, dev.m.ArrayXf(*columns), dev.arange(n))
    return out


def read_rows(dev, table, index, width: int, active=True) -> list:
    """Rows ``index`` (UInt32 per lane) of a flat Float table of rows of ``width`` values (:func:`float_rows`), by
    one packet gather: ``width`` Float arrays."""
    return dev.dr.gather(dev.m.ArrayXf, table, index, active, shape=(width, dev.dr.width(index)))


class SceneTables:
    """The scene's per-vertex, per-face and per-material data on the device, as the G-buffer and the alpha test read
    them: world vertex positions and shading normals at the tracer's time (float32, moving vertices updated on
    ``tracer.update``), UVs, faces, per-face material and object, per-material albedo, emission, kind code, albedo
    and opacity textures (flat, Mitsuba's bitmap layout), alpha thresholds."""

    def __init__(self, device: Device):
        from suite.core.scene.model import KIND_CODES

        dev = self.dev = device
        scene = device.scene
        F, U, I = dev.Float, dev.UInt32, dev.Int32
        t_s = device.tracer._time_s
        positions = scene.positions_at(t_s)
        normals = scene.normals_at(t_s)
        # Vertex positions, normals and faces in rows of four (the fourth unused), UVs in rows of two: a packet gather
        # (Dr.Jit's dr.gather of a power-of-two row) reads a row in a few vector loads where a gather per value
        # costs a gather instruction each.
        self.vpos = dev.to_device(packet_rows([positions], np.float32, ROW), F)
        self.vnrm = dev.to_device(packet_rows([normals], np.float32, ROW), F)
        self.vuv = dev.to_device(np.ascontiguousarray(scene.uvs, np.float32).reshape(-1), F)
        self.faces = dev.to_device(packet_rows([scene.faces], np.uint32, ROW), U)
        self.face_material = dev.to_device(np.ascontiguousarray(scene.face_material, np.int32), I)
        self.face_object = dev.to_device(np.ascontiguousarray(scene.face_object, np.int32), I)
        mats = scene.materials
        self.albedo = dev.to_device(np.stack([m.albedo for m in mats]).astype(np.float32).reshape(-1), F)
        self.emission = dev.to_device(np.stack([m.emission for m in mats]).astype(np.float32).reshape(-1), F)
        self.kind = dev.to_device(np.array([KIND_CODES[m.shading_kind] for m in mats], np.int32), I)
        self.any_emissive = any(m.is_emissive for m in mats)
        self.albedo_tex = _TextureTable(dev, [m.albedo_texture for m in mats], 3)
        self.opacity_tex = _TextureTable(dev, [m.opacity_texture if m.is_alpha_tested else None for m in mats], 1)
        self.threshold = dev.to_device(np.array([m.alpha_threshold if m.is_alpha_tested else 0.0 for m in mats],
                                                np.float32), F)
        tested = np.array([m.is_alpha_tested for m in mats], np.uint32)
        self.face_tested = dev.to_device(tested[scene.face_material], U) if tested.any() else None
        # Vertices of animated objects (their rows are re-uploaded on update).
        moving = {a.object_id for a in scene.object_animations}
        if moving:
            dyn_faces = np.isin(scene.face_object, list(moving))
            self.dynamic_vertices = np.unique(scene.faces[dyn_faces].reshape(-1)).astype(np.uint32)
        else:
            self.dynamic_vertices = np.zeros(0, np.uint32)
        self._dyn_index = None
        self.time_s = t_s
        dev.dr.eval(self.vpos, self.vnrm, self.vuv, self.faces, self.face_material, self.face_object)

    def update(self, positions_world: np.ndarray, t_s: float) -> None:
        """Moves the animated vertices to their positions (and normals) at ``t_s``."""
        if len(self.dynamic_vertices) == 0:
            return
        dev, dr = self.dev, self.dev.dr
        rows = self.dynamic_vertices
        if self._dyn_index is None:
            idx = (rows[:, None].astype(np.uint32) * ROW + np.arange(3, dtype=np.uint32)).reshape(-1)
            self._dyn_index = dev.to_device(idx, dev.UInt32)
        normals = dev.scene.normals_at(t_s)
        p = dev.to_device(np.ascontiguousarray(positions_world[rows], np.float32).reshape(-1), dev.Float)
        n = dev.to_device(np.ascontiguousarray(normals[rows], np.float32).reshape(-1), dev.Float)
        dr.scatter(self.vpos, p, self._dyn_index)
        dr.scatter(self.vnrm, n, self._dyn_index)
        dr.eval(self.vpos, self.vnrm)
        self.time_s = t_s

    # ---------------------------------------------------------------------------------------------- lookups
    def triangle(self, prim, active):
        """Vertex indices (3 UInt32) of faces ``prim`` (one packet gather of the face's row)."""
        dr, U = self.dev.dr, self.dev.UInt32
        row = dr.gather(self.dev.m.ArrayXu, self.faces, U(dr.maximum(prim, 0)), active, shape=(ROW, dr.width(prim)))
        return [row[k] for k in range(3)]

    def vertex(self, table, vid, active):
        """Vector3f rows ``vid`` of ``vpos`` or ``vnrm`` (one packet gather each)."""
        dev = self.dev
        row = dev.dr.gather(dev.m.ArrayXf, table, vid, active, shape=(ROW, dev.dr.width(vid)))
        return dev.Vector3f(row[0], row[1], row[2])

    def uv_f64(self, vids, w, active):
        """Interpolated float64 texture coordinates ``(uv0 w0 + uv1 w1) + uv2 w2`` (numpy's order)."""
        dev = self.dev
        uv = [dev.dr.gather(dev.m.ArrayXf, self.vuv, vid, active, shape=(2, dev.dr.width(vid))) for vid in vids]
        uv = [dev.Point2f(r[0], r[1]) for r in uv]
        x = (dev.Float64(uv[0].x) * w[0] + dev.Float64(uv[1].x) * w[1]) + dev.Float64(uv[2].x) * w[2]
        y = (dev.Float64(uv[0].y) * w[0] + dev.Float64(uv[1].y) * w[1]) + dev.Float64(uv[2].y) * w[2]
        return x, y

    def front_emission(self, mat, front):
        """Vector3f: the radiance of materials ``mat`` toward rays that met their emitting side (``front``), 0 elsewhere
        and in a scene without emitters."""
        dev, dr = self.dev, self.dev.dr
        if not self.any_emissive:
            return dr.zeros(dev.Vector3f, dr.width(mat))
        return dr.select(front, dr.gather(dev.Vector3f, self.emission, dr.maximum(mat, 0), front),
                         dev.Vector3f(0.0, 0.0, 0.0))

    def tested_face(self, prim, active):
        """Bool: the hit lies on a face whose material is alpha-tested (one gather of a per-face flag)."""
        dev, dr = self.dev, self.dev.dr
        hit = active & (prim >= 0)
        return hit & (dr.gather(dev.UInt32, self.face_tested, dr.maximum(prim, 0), hit) != 0)

    def transparent(self, prim, u, v, active):
        """Bool: the hit lies where its material's opacity is below its threshold (:meth:`AlphaTest.transparent`)."""
        dev, dr = self.dev, self.dev.dr
        hit = active & (prim >= 0)
        mat = dr.gather(dev.Int32, self.face_material, dr.maximum(prim, 0), hit)
        tested = hit & self.opacity_tex.has(mat, hit)
        F64 = dev.Float64
        u64, v64 = F64(u), F64(v)
        w = (1.0 - u64 - v64, u64, v64)  # float64, as AlphaTest.opacity computes it
        uvx, uvy = self.uv_f64(self.triangle(prim, tested), w, tested)
        opacity = self.opacity_tex.lookup(mat, uvx, uvy, tested)[0]
        threshold = dr.gather(dev.Float, self.threshold, mat, tested)
        return tested & (opacity < threshold)


class _TextureTable:
    """Per-material textures in one flat float32 array: offset, width, height and channels per material (width 0:
    none). Lookups are :func:`suite.core.gbuffer.lookup_texture` (bilinear, repeating, texel centres at +0.5, row 0
    at v = 0) operation for operation in float64; a single-channel texture gives its value in every channel asked
    for (a grey albedo map, as the host's ``_texel`` reads it)."""

    def __init__(self, dev: Device, textures, channels: int):
        self.dev, self.channels = dev, channels
        # Several channels: every texel as a row of four (the channels the lookup reads, a grey texture's value
        # repeated, padding), read by one packet gather per texel; offsets then count rows.
        self.packed = channels > 1
        offsets, widths, heights, stored, chunks, at = [], [], [], [], [], 0
        for tex in textures:
            if tex is None:
                offsets.append(0), widths.append(0), heights.append(0), stored.append(1)
                continue
            tex = np.ascontiguousarray(tex, np.float32).reshape(tex.shape[0], tex.shape[1], -1)[:, :, :channels]
            offsets.append(at), widths.append(tex.shape[1]), heights.append(tex.shape[0]), stored.append(tex.shape[2])
            if self.packed:
                texels = tex.reshape(-1, tex.shape[2])
                # the channel the lookup reads for channel j (the first where there is no j)
                chunks.append(packet_rows([texels[:, [j if tex.shape[2] > j else 0 for j in range(channels)]]],
                                          np.float32, ROW))
                at += len(texels)
            else:
                chunks.append(tex.reshape(-1))
                at += tex.size
        self.any = bool(chunks)
        self.offset = dev.to_device(np.array(offsets, np.uint32), dev.UInt32)
        self.width = dev.to_device(np.array(widths, np.int32), dev.Int32)
        self.height = dev.to_device(np.array(heights, np.int32), dev.Int32)
        self.stored = dev.to_device(np.array(stored, np.uint32), dev.UInt32)   # channels kept per texel
        self.data = dev.to_device(np.concatenate(chunks) if chunks else np.zeros(1, np.float32), dev.Float)

    def has(self, mat, active):
        if not self.any:
            return self.dev.Bool(False)
        return self.dev.dr.gather(self.dev.Int32, self.width, mat, active) > 0

    def lookup(self, mat, uvx, uvy, active):
        """``channels`` Float64 values at float64 UVs (for materials with a texture; garbage-free zeros elsewhere)."""
        dev, dr = self.dev, self.dev.dr
        F64, I, U = dev.Float64, dev.Int32, dev.UInt32
        w_i = dr.gather(I, self.width, mat, active)
        h_i = dr.gather(I, self.height, mat, active)
        active = active & (w_i > 0)
        off = dr.gather(U, self.offset, mat, active)
        w, h = F64(w_i), F64(h_i)
        x = uvx * w - 0.5
        y = uvy * h - 0.5
        x0, y0 = dr.floor(x), dr.floor(y)
        fx, fy = x - x0, y - y0
        # Python's modulo (non-negative) of the integer texel coordinates, exact in float64.
        x0m = x0 - w * dr.floor(x0 / w)
        y0m = y0 - h * dr.floor(y0 / h)
        x0i = dr.clip(I(x0m), 0, w_i - 1)
        y0i = dr.clip(I(y0m), 0, h_i - 1)
        x1i = dr.select(x0i + 1 >= w_i, 0, x0i + 1)
        y1i = dr.select(y0i + 1 >= h_i, 0, y0i + 1)
        wu = U(w_i)
        a00, a10 = (1.0 - fx) * (1.0 - fy), fx * (1.0 - fy)
        a01, a11 = (1.0 - fx) * fy, fx * fy
        out = []
        if self.packed:
            n = dr.width(mat)
            t = [dr.gather(dev.m.ArrayXf, self.data, off + U(yi) * wu + U(xi), active, shape=(ROW, n))
                 for yi, xi in ((y0i, x0i), (y0i, x1i), (y1i, x0i), (y1i, x1i))]
            for channel in range(self.channels):
                val = ((a00 * F64(t[0][channel]) + a10 * F64(t[1][channel])) + a01 * F64(t[2][channel])) \
                    + a11 * F64(t[3][channel])
                out.append(dr.select(active, val, 0.0))
            return out
        c = dr.gather(U, self.stored, mat, active)

        def texel(yi, xi, k):
            return F64(dr.gather(dev.Float, self.data, off + (U(yi) * wu + U(xi)) * c + k, active))

        for channel in range(self.channels):
            k = dr.select(c > channel, U(channel), U(0))
            val = ((a00 * texel(y0i, x0i, k) + a10 * texel(y0i, x1i, k)) + a01 * texel(y1i, x0i, k)) \
                + a11 * texel(y1i, x1i, k)
            out.append(dr.select(active, val, 0.0))
        return out
