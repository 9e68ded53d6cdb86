"""Quake III IBSP version 46 files, read into numpy structured arrays.

Layout (id Software's ``qfiles.h``, the format q3map2 writes): a header of the magic ``IBSP``, the version 46 and
17 lump directory entries ``(offset, length)`` in bytes, then the lumps. Every lump is an array of fixed-size
little-endian records except the entity text and the visibility data.

Validation: the magic, the version, every lump's offset and length against the file size, record-size
multiples, and every index a later stage follows (face -> vertexes / meshverts / shader, leaf -> leaffaces,
leafface -> face, node -> plane / children, model -> faces, visdata size, patch dimensions). A malformed or
truncated file raises one :class:`~suite.errors.UserError` line that names the file and the problem.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError

MAGIC = b"IBSP"
VERSION = 46
LUMP_NAMES = ("entities", "shaders", "planes", "nodes", "leafs", "leaffaces", "leafbrushes", "models", "brushes",
              "brushsides", "vertexes", "meshverts", "effects", "faces", "lightmaps", "lightvols", "visdata")
HEADER_BYTES = 8 + 8 * len(LUMP_NAMES)

# Face (draw surface) types, qfiles.h mapSurfaceType_t.
MST_BAD, MST_PLANAR, MST_PATCH, MST_TRIANGLE_SOUP, MST_FLARE = 0, 1, 2, 3, 4
FACE_TYPE_NAMES = {MST_BAD: "bad", MST_PLANAR: "planar", MST_PATCH: "patch", MST_TRIANGLE_SOUP: "mesh",
                   MST_FLARE: "billboard"}

DTYPES = {
    "shaders": np.dtype([("name", "S64"), ("flags", "<i4"), ("contents", "<i4")]),
    "planes": np.dtype([("normal", "<f4", 3), ("dist", "<f4")]),
    "nodes": np.dtype([("plane", "<i4"), ("children", "<i4", 2), ("mins", "<i4", 3), ("maxs", "<i4", 3)]),
    "leafs": np.dtype([("cluster", "<i4"), ("area", "<i4"), ("mins", "<i4", 3), ("maxs", "<i4", 3),
                       ("leafface", "<i4"), ("n_leaffaces", "<i4"), ("leafbrush", "<i4"), ("n_leafbrushes", "<i4")]),
    "leaffaces": np.dtype("<i4"),
    "leafbrushes": np.dtype("<i4"),
    "models": np.dtype([("mins", "<f4", 3), ("maxs", "<f4", 3), ("face", "<i4"), ("n_faces", "<i4"),
                        ("brush", "<i4"), ("n_brushes", "<i4")]),
    "brushes": np.dtype([("brushside", "<i4"), ("n_brushsides", "<i4"), ("shader", "<i4")]),
    "brushsides": np.dtype([("plane", "<i4"), ("shader", "<i4")]),
    "vertexes": np.dtype([("position", "<f4", 3), ("texcoord", "<f4", 2), ("lmcoord", "<f4", 2),
                          ("normal", "<f4", 3), ("color", "u1", 4)]),
    "meshverts": np.dtype("<i4"),
    "effects": np.dtype([("name", "S64"), ("brush", "<i4"), ("visible_side", "<i4")]),
    "faces": np.dtype([("shader", "<i4"), ("effect", "<i4"), ("type", "<i4"), ("vertex", "<i4"),
                       ("n_vertexes", "<i4"), ("meshvert", "<i4"), ("n_meshverts", "<i4"), ("lm_index", "<i4"),
                       ("lm_start", "<i4", 2), ("lm_size", "<i4", 2), ("lm_origin", "<f4", 3),
                       ("lm_vecs", "<f4", (2, 3)), ("normal", "<f4", 3), ("size", "<i4", 2)]),
}
assert DTYPES["faces"].itemsize == 104 and DTYPES["vertexes"].itemsize == 44 and DTYPES["leafs"].itemsize == 48


@dataclass
class Visdata:
    """The cluster PVS as stored: ``n_clusters`` rows of ``row_bytes`` bytes; bit ``j`` of row ``i``
    (byte ``j >> 3``, bit ``j & 7``) says cluster ``j`` is potentially visible from cluster ``i``."""

    n_clusters: int
    row_bytes: int
    rows: np.ndarray  # (n_clusters, row_bytes) uint8

    def matrix(self) -> np.ndarray:
        """(C, C) bool, ``m[i, j]``: cluster j is potentially visible from cluster i."""
        bits = np.unpackbits(self.rows, axis=1, bitorder="little")
        return bits[:, :self.n_clusters].astype(bool)


@dataclass
class BspFile:
    """The lumps of one IBSP v46 file. Record lumps are numpy structured arrays (see ``DTYPES``)."""

    name: str
    size_bytes: int
    entities_text: str
    entities: list[dict[str, str]]
    shaders: np.ndarray
    planes: np.ndarray
    nodes: np.ndarray
    leafs: np.ndarray
    leaffaces: np.ndarray
    leafbrushes: np.ndarray
    models: np.ndarray
    brushes: np.ndarray
    brushsides: np.ndarray
    vertexes: np.ndarray
    meshverts: np.ndarray
    effects: np.ndarray
    faces: np.ndarray
    visdata: Visdata | None
    lump_bytes: dict[str, int] = field(default_factory=dict)

    @property
    def shader_names(self) -> list[str]:
        return [n.split(b"\0", 1)[0].decode("latin-1") for n in self.shaders["name"]]

    @property
    def n_clusters(self) -> int:
        if self.visdata is not None:
            return self.visdata.n_clusters
        return int(self.leafs["cluster"].max()) + 1 if len(self.leafs) else 0

    def face_type_counts(self) -> dict[str, int]:
        types, counts = np.unique(self.faces["type"], return_counts=True)
        return {FACE_TYPE_NAMES.get(int(t), f"type{int(t)}"): int(c) for t, c in zip(types, counts)}


def _fail(name: str, problem: str):
    raise UserError(f"{name}: not a valid Quake III BSP (IBSP v46): {problem}")


_TOKEN = re.compile(r'"([^"]*)"|([{}])|(\S+)')


def parse_entities(text: str, name: str = "bsp") -> list[dict[str, str]]:
    """The entity lump: ``{ "key" "value" ... }`` blocks. Keys are case-sensitive as written; a repeated key
    keeps its last value (as the game's spawn code does)."""
    entities: list[dict[str, str]] = []
    current: dict[str, str] | None = None
    key: str | None = None
    for m in _TOKEN.finditer(text):
        quoted, brace, bare = m.groups()
        if brace == "{":
            if current is not None:
                _fail(name, f"entity lump: '{{' inside an entity at character {m.start()}")
            current, key = {}, None
        elif brace == "}":
            if current is None or key is not None:
                _fail(name, f"entity lump: unbalanced '}}' at character {m.start()}")
            entities.append(current)
            current = None
        elif quoted is not None:
            if current is None:
                _fail(name, f"entity lump: text outside an entity at character {m.start()}")
            if key is None:
                key = quoted
            else:
                current[key] = quoted
                key = None
        elif bare is not None:
            if bare.strip("\0"):
                _fail(name, f"entity lump: unexpected token '{bare[:20]}' at character {m.start()}")
    if current is not None:
        _fail(name, "entity lump: the last entity is not closed")
    return entities


def _check_range(name, what, start, count, limit):
    """Every [start, start + count) must lie inside [0, limit)."""
    start = np.asarray(start, np.int64)
    count = np.asarray(count, np.int64)
    bad = (start < 0) | (count < 0) | (start + count > limit)
    if bad.any():
        i = int(np.argmax(bad))
        _fail(name, f"{what} {i} refers to records {int(start.flat[i])}..{int(start.flat[i] + count.flat[i]) - 1}"
                    f" outside 0..{limit - 1}")


def _check_index(name, what, values, limit, allow_negative=False):
    values = np.asarray(values, np.int64)
    bad = (values >= limit) | ((values < 0) if not allow_negative else (values < -limit - 1))
    if bad.any():
        i = int(np.argmax(bad.reshape(-1)))
        _fail(name, f"{what} (entry {i}) = {int(values.reshape(-1)[i])} is out of range 0..{limit - 1}")


def parse_bsp(data: bytes, name: str = "bsp") -> BspFile:
    """Parses and validates an IBSP v46 file held in memory."""
    size = len(data)
    if size < HEADER_BYTES:
        _fail(name, f"file is {size} bytes, shorter than the {HEADER_BYTES}-byte header")
    if data[:4] != MAGIC:
        _fail(name, f"magic is {data[:4]!r}, expected {MAGIC!r}")
    version = int(np.frombuffer(data, "<i4", 1, 4)[0])
    if version != VERSION:
        _fail(name, f"version {version}, expected {VERSION} (Quake III / OpenArena)")
    directory = np.frombuffer(data, "<i4", 2 * len(LUMP_NAMES), 8).reshape(-1, 2).astype(np.int64)
    lumps: dict[str, bytes] = {}
    for lump, (offset, length) in zip(LUMP_NAMES, directory):
        if offset < 0 or length < 0:
            _fail(name, f"lump '{lump}' has a negative offset or length ({offset}, {length})")
        if length and offset < HEADER_BYTES:
            _fail(name, f"lump '{lump}' starts at byte {offset}, inside the header")
        if offset + length > size:
            _fail(name, f"lump '{lump}' (offset {offset}, length {length}) extends past the end of the file "
                        f"({size} bytes): truncated?")
        lumps[lump] = data[offset:offset + length]

    arrays = {}
    for lump, dtype in DTYPES.items():
        raw = lumps[lump]
        if len(raw) % dtype.itemsize:
            _fail(name, f"lump '{lump}' is {len(raw)} bytes, not a multiple of its {dtype.itemsize}-byte record")
        arrays[lump] = np.frombuffer(raw, dtype)

    text = lumps["entities"].split(b"\0", 1)[0].decode("latin-1")
    entities = parse_entities(text, name)

    vis = None
    raw = lumps["visdata"]
    if len(raw):
        if len(raw) < 8:
            _fail(name, f"lump 'visdata' is {len(raw)} bytes, shorter than its 8-byte header")
        n_vecs, sz_vecs = (int(x) for x in np.frombuffer(raw, "<i4", 2))
        if n_vecs < 0 or sz_vecs < 0 or 8 + n_vecs * sz_vecs > len(raw):
            _fail(name, f"visdata claims {n_vecs} clusters x {sz_vecs} bytes but the lump has {len(raw) - 8} bytes")
        if sz_vecs * 8 < n_vecs:
            _fail(name, f"visdata rows of {sz_vecs} bytes cannot hold {n_vecs} cluster bits")
        vis = Visdata(n_vecs, sz_vecs, np.frombuffer(raw, np.uint8, n_vecs * sz_vecs, 8).reshape(n_vecs, sz_vecs))

    bsp = BspFile(name=name, size_bytes=size, entities_text=text, entities=entities,
                  visdata=vis, lump_bytes={k: len(v) for k, v in lumps.items()}, **arrays)
    _validate(bsp)
    return bsp


def _validate(b: BspFile) -> None:
    name = b.name
    nv, nm, nf, ns = len(b.vertexes), len(b.meshverts), len(b.faces), len(b.shaders)
    nl, nn, npl, nlf = len(b.leafs), len(b.nodes), len(b.planes), len(b.leaffaces)
    if nf == 0:
        _fail(name, "no faces")
    if len(b.models) == 0:
        _fail(name, "no models (model 0 is the world)")
    if nl == 0:
        _fail(name, "no leafs")
    f = b.faces
    _check_index(name, "face shader", f["shader"], ns)
    _check_range(name, "face", f["vertex"], f["n_vertexes"], nv)
    _check_range(name, "face", f["meshvert"], f["n_meshverts"], nm)
    # Effects (fog volumes) are referenced by index or -1.
    _check_index(name, "face effect", np.where(f["effect"] < 0, 0, f["effect"]), max(len(b.effects), 1))
    drawn = (f["type"] == MST_PLANAR) | (f["type"] == MST_TRIANGLE_SOUP)
    if (f["n_meshverts"][drawn] % 3).any():
        i = int(np.nonzero(drawn & (f["n_meshverts"] % 3 != 0))[0][0])
        _fail(name, f"face {i} has {int(f['n_meshverts'][i])} meshverts, not a multiple of 3")
    if drawn.any() and nm:
        # Meshverts are offsets into the face's own vertex range.
        owner = np.repeat(np.nonzero(drawn)[0], f["n_meshverts"][drawn])
        mv = _gather_ranges(b.meshverts, f["meshvert"][drawn], f["n_meshverts"][drawn])
        bad = (mv < 0) | (mv >= f["n_vertexes"][owner])
        if bad.any():
            k = int(np.argmax(bad))
            _fail(name, f"face {int(owner[k])}: meshvert {int(mv[k])} is outside its "
                        f"{int(f['n_vertexes'][owner[k]])} vertexes")
    patch = f["type"] == MST_PATCH
    if patch.any():
        w, h = f["size"][patch, 0], f["size"][patch, 1]
        bad = (w < 3) | (h < 3) | (w % 2 == 0) | (h % 2 == 0) | (w * h != f["n_vertexes"][patch])
        if bad.any():
            i = int(np.nonzero(patch)[0][np.argmax(bad)])
            _fail(name, f"patch face {i} has a {int(f['size'][i, 0])}x{int(f['size'][i, 1])} control grid "
                        f"(odd sizes >= 3 with width*height = {int(f['n_vertexes'][i])} vertexes expected)")
    if not np.isfinite(b.vertexes["position"]).all():
        _fail(name, "vertex positions contain NaN or Inf")
    _check_range(name, "model", b.models["face"], b.models["n_faces"], nf)
    _check_range(name, "leaf", b.leafs["leafface"], b.leafs["n_leaffaces"], nlf)
    _check_index(name, "leafface", b.leaffaces, nf)
    _check_index(name, "node plane", b.nodes["plane"], npl)
    children = b.nodes["children"]
    bad = (children >= nn) | (children < -nl)  # >= 0: node index; < 0: leaf -(child + 1)
    if bad.any():
        i = int(np.argmax(bad.reshape(-1)))
        _fail(name, f"node child (entry {i}) = {int(children.reshape(-1)[i])} is neither a node (< {nn}) "
                    f"nor a leaf (>= {-nl})")
    # q3map2 emits nodes in pre-order (EmitDrawNode), so a child node always has a larger index than its
    # parent; requiring it rules out cycles, and a point lookup ends within the tree's depth.
    own = np.arange(nn)[:, None]
    if ((children >= 0) & (children <= own)).any():
        i = int(np.argmax(((children >= 0) & (children <= own)).any(axis=1)))
        _fail(name, f"node {i} has a child node that does not come after it (the tree has a cycle)")
    if b.visdata is not None:
        c = b.leafs["cluster"]
        if (c >= b.visdata.n_clusters).any():
            _fail(name, f"leaf cluster {int(c.max())} exceeds the {b.visdata.n_clusters} clusters in visdata")
    if (b.leafs["cluster"] < -1).any():
        _fail(name, f"leaf cluster {int(b.leafs['cluster'].min())} is below -1")


def _gather_ranges(values: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenation of ``values[s:s+c]`` for every (s, c), without a Python loop."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, values.dtype)
    ends = np.cumsum(counts)
    offsets = np.repeat(np.asarray(starts, np.int64) - (ends - counts), counts)
    return values[np.arange(total) + offsets]


gather_ranges = _gather_ranges


def pack_bsp(lumps: dict, version: int = VERSION, magic: bytes = MAGIC) -> bytes:
    """An IBSP file from lumps given by name: numpy arrays (stored as their bytes), ``bytes``, or ``str``
    (the entity text, NUL-terminated here). Missing lumps are empty. The inverse of :func:`parse_bsp`, for
    tests and tiny hand-made maps."""
    unknown = set(lumps) - set(LUMP_NAMES)
    if unknown:
        raise UserError(f"unknown BSP lump(s) {sorted(unknown)}")
    blobs = []
    for lump in LUMP_NAMES:
        value = lumps.get(lump, b"")
        if isinstance(value, str):
            value = value.encode("latin-1") + b"\0"
        elif isinstance(value, np.ndarray):
            value = value.tobytes()
        blobs.append(bytes(value))
    header = bytearray(magic + np.int32(version).tobytes())
    offset = HEADER_BYTES
    body = bytearray()
    for blob in blobs:
        header += np.array([offset if blob else 0, len(blob)], "<i4").tobytes()
        body += blob + b"\0" * (-len(blob) % 4)
        offset += len(blob) + (-len(blob) % 4)
    return bytes(header + body)


def visdata_bytes(matrix: np.ndarray) -> bytes:
    """The visdata lump of a (C, C) bool PVS matrix (row i: clusters visible from cluster i)."""
    m = np.asarray(matrix, bool)
    n = len(m)
    row_bytes = max(1, (n + 7) // 8)
    rows = np.packbits(np.pad(m, ((0, 0), (0, row_bytes * 8 - n))), axis=1, bitorder="little")
    return np.array([n, row_bytes], "<i4").tobytes() + rows.tobytes()
