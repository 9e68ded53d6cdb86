"""Wavefront OBJ geometry through tinyobjloader, checked before anything uses it.

Parsing is tinyobjloader's (the official Python bindings, ``pip install tinyobjloader``; polygons are
triangulated by it). This module adds what the library leaves to its caller:

* **Statement check** (:func:`census`): a vectorised pass over the file's bytes classifies every line by its
  keyword. ``v``/``vn``/``vt``/``f`` lines must have the right number of fields and only numeric characters
  (tinyobjloader reads a missing or malformed number as 0); this catches files cut off in the middle of a line.
  Statements of the OBJ specification that the suite does not model (lines ``l``, points ``p``, free-form
  curves and surfaces ``vp``/``curv``/``surf``/..., ``lod``, ``usemap``, ...) are counted; a keyword that is not
  an OBJ statement at all makes the file malformed.
* **Index check**: every corner's vertex index must exist (tinyobjloader only warns), normal and texture indices
  too.
* **Vertices**: OBJ corners index positions, normals and texture coordinates separately; the model has one
  index per vertex, so each distinct (position, normal, texcoord) triple becomes one vertex. Corners without a
  normal get their triangle's geometric normal (flat shading; counted). Texture coordinates are flipped to the
  model's layout: ``(u, 1 - v)`` (OBJ puts v = 0 at the image's bottom row, the model at row 0 = the top row;
  Mitsuba's own OBJ loader does the same flip).
* **NumPy 2**: the 2.0.0rc13 wheels return their ``numpy_*`` arrays with a zero stride under NumPy 2 (the data
  is copied correctly, the stride is computed from NumPy 1's descriptor layout; tinyobjloader issue #401).
  :func:`_array` restores the stride; a self-test on a small file at first use falls back to the (slower)
  list accessors if a future wheel behaves differently.

Problems raise one-line :class:`~suite.errors.UserError`\\ s: ``<file>: not a valid OBJ file: <problem>``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.errors import UserError

# Statements tinyobjloader reads and the suite uses (or which carry no geometry).
KNOWN = {"v", "vn", "vt", "f", "o", "g", "s", "usemtl", "mtllib"}
# Statements of the OBJ specification (and tinyobjloader's extensions) whose content the suite does not model.
UNSUPPORTED = {"l", "p", "vp", "vw", "t", "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm",
               "trim", "hole", "scrv", "sp", "end", "con", "mg", "bevel", "c_interp", "d_interp", "lod", "usemap",
               "maplib", "shadow_obj", "trace_obj", "ctech", "stech", "call", "csh"}
# (min, max) whitespace-separated fields, keyword included, of the numeric statements.
FIELDS = {"v": (4, 7), "vn": (4, 4), "vt": (2, 4), "f": (4, 1 << 30)}

_BYTE_CLASS = np.full(256, 64, np.int32)  # 0: digit / sign / point / exponent / slash / whitespace; 1: letter; 64: other
for _c in b"0123456789+-./eE \t\r\n":
    _BYTE_CLASS[_c] = 0
for _c in b"abcdfghijklmnopqrstuvwxyzABCDFGHIJKLMNOPQRSTUVWXYZ_":
    _BYTE_CLASS[_c] = 1
_CLASS_WEIGHT = (np.minimum(_BYTE_CLASS, 64) << 10).astype(np.int32)  # weights of :func:`_line_sums`
_SEPARATOR = np.zeros(256, bool)
for _c in b" \t\r\n":
    _SEPARATOR[_c] = True


def invalid(path, problem: str) -> UserError:
    return UserError(f"{path}: not a valid OBJ file: {problem}")


@dataclass
class Census:
    """Line counts by statement, the ``mtllib`` files, and counts of statements the suite does not model."""

    lines: int = 0
    counts: dict = field(default_factory=dict)  # keyword -> number of lines
    unsupported: dict = field(default_factory=dict)  # keyword -> number of lines
    mtllibs: list = field(default_factory=list)


def census(data: bytes, path) -> Census:
    """Classifies every line of an OBJ file (vectorised over lines); raises on malformed statements."""
    out = Census()
    if not data:
        return out
    arr = np.frombuffer(data, np.uint8)
    newline = np.flatnonzero(arr == 10)
    starts = np.concatenate([[0], newline + 1]).astype(np.int64)
    if starts[-1] >= len(arr):
        starts = starts[:-1]
    out.lines = len(starts)
    padded = np.concatenate([arr, np.zeros(3, np.uint8)])
    c0, c1, c2 = padded[starts], padded[starts + 1], padded[starts + 2]
    sep1, sep2 = _SEPARATOR[c1], _SEPARATOR[c2]
    is_v = (c0 == ord("v")) & sep1
    is_vn = (c0 == ord("v")) & (c1 == ord("n")) & sep2
    is_vt = (c0 == ord("v")) & (c1 == ord("t")) & sep2
    is_f = (c0 == ord("f")) & sep1
    blank = (c0 == 10) | (c0 == 13)
    comment = c0 == ord("#")
    numeric = is_v | is_vn | is_vt | is_f
    for name, mask in (("v", is_v), ("vn", is_vn), ("vt", is_vt), ("f", is_f)):
        n = int(mask.sum())
        if n:
            out.counts[name] = n

    if numeric.any():
        n_fields, chars = _line_sums(arr, starts)
        letters_allowed = np.where(is_vn | is_vt, 2, 1)
        bad = numeric & (chars != letters_allowed)
        for name, mask in (("v", is_v), ("vn", is_vn), ("vt", is_vt), ("f", is_f)):
            lo, hi = FIELDS[name]
            bad |= mask & ((n_fields < lo) | (n_fields > hi))
        for i in np.flatnonzero(bad):  # candidates; a trailing comment is allowed
            text = _line(data, starts, int(i))
            if not _valid_numeric(text):
                kw = text.split()[0] if text.split() else "?"
                last = " (the file ends inside this line: truncated?)" if i == len(starts) - 1 else ""
                raise invalid(path, f"line {int(i) + 1}: malformed '{kw}' statement {text[:80]!r}{last}")

    others = np.flatnonzero(~(numeric | blank | comment))
    for i in others:
        text = _line(data, starts, int(i))
        words = text.split()
        if not words or words[0].startswith("#"):
            continue
        kw = words[0]
        if kw in KNOWN:
            out.counts[kw] = out.counts.get(kw, 0) + 1
            if kw == "mtllib":
                out.mtllibs += words[1:]
        elif kw in UNSUPPORTED:
            out.unsupported[kw] = out.unsupported.get(kw, 0) + 1
        else:
            raise invalid(path, f"line {int(i) + 1}: unknown statement {text[:80]!r}")
    return out


def _line_sums(arr: np.ndarray, starts: np.ndarray, chunk_bytes: int = 1 << 23):
    """Per line: the number of whitespace-separated fields and the character-class sum (letters count 1, bytes
    that belong in no OBJ number 64). Vectorised in chunks of whole lines (bounded memory): each byte gets a
    weight ``field_start + 1024 * class``, summed per line. A line with 1024 fields or more spills into the class
    count and is re-checked exactly by :func:`_valid_numeric`."""
    n_lines = len(starts)
    bounds = np.append(starts, len(arr))
    total = np.empty(n_lines, np.int64)
    i0 = 0
    while i0 < n_lines:
        i1 = int(np.searchsorted(bounds, bounds[i0] + chunk_bytes, side="right")) - 1
        i1 = min(max(i1, i0 + 1), n_lines)
        a, b = int(bounds[i0]), int(bounds[i1])
        seg = arr[a:b]
        sep = _SEPARATOR[seg]
        w = _CLASS_WEIGHT[seg]
        w[1:] += sep[:-1] > sep[1:]  # a field starts where a separator is followed by anything else
        w[0] += not sep[0]
        total[i0:i1] = np.add.reduceat(w, bounds[i0:i1] - a, dtype=np.int64)
        i0 = i1
    return total & 1023, total >> 10


def _valid_numeric(text: str) -> bool:
    """Full check of one ``v``/``vn``/``vt``/``f`` line (comment after ``#`` removed)."""
    words = text.split("#", 1)[0].split()
    if not words or words[0] not in FIELDS:
        return False
    lo, hi = FIELDS[words[0]]
    if not lo <= len(words) <= hi:
        return False
    try:
        if words[0] == "f":
            for w in words[1:]:
                parts = w.split("/")
                if len(parts) > 3 or not parts[0] or any(p and int(p) == 0 for p in parts):
                    return False
        else:
            values = [float(w) for w in words[1:]]
            return all(np.isfinite(values))
    except ValueError:
        return False
    return True


def _line(data: bytes, starts: np.ndarray, i: int) -> str:
    a = int(starts[i])
    b = int(starts[i + 1]) if i + 1 < len(starts) else len(data)
    return data[a:b].decode("utf-8", "replace").strip()


# --- tinyobjloader -------------------------------------------------------------------------------------

_ARRAYS_OK: bool | None = None


def _array(fetch, fallback, dtype) -> np.ndarray:
    """A tinyobjloader ``numpy_*`` result as an owned contiguous array (see the module docstring)."""
    if _ARRAYS_OK is False:
        return np.asarray(fallback(), dtype)
    a = fetch()
    if a.ndim == 1 and a.size > 1 and a.strides[0] != a.itemsize:
        a = np.lib.stride_tricks.as_strided(a, shape=a.shape, strides=(a.itemsize,))
    return np.array(a, dtype)


def _self_test() -> bool:
    """Whether the stride-restored numpy accessors return what the list accessors return."""
    import tempfile

    import tinyobjloader

    text = "v 0.5 1.5 2.5\nv 3 4 5\nv 6 7 8\nvn 0 0 1\nvt 0.25 0.75\nf 1/1/1 2/1/1 3/1/1\n"
    with tempfile.TemporaryDirectory() as tmp:
        p = os.path.join(tmp, "t.obj")
        with open(p, "w") as fh:
            fh.write(text)
        r = tinyobjloader.ObjReader()
        if not r.ParseFromFile(p, tinyobjloader.ObjReaderConfig()):
            return False
        attrib, shapes = r.GetAttrib(), r.GetShapes()
        global _ARRAYS_OK
        _ARRAYS_OK = True
        try:
            v = _array(attrib.numpy_vertices, lambda: attrib.vertices, np.float64)
            idx = _array(shapes[0].mesh.numpy_indices, None, np.int64)
        finally:
            _ARRAYS_OK = None
        want_idx = [x for i in shapes[0].mesh.indices for x in (i.vertex_index, i.normal_index, i.texcoord_index)]
        return v.tolist() == list(attrib.vertices) and idx.tolist() == want_idx


def _indices_fallback(mesh):
    return [x for i in mesh.indices for x in (i.vertex_index, i.normal_index, i.texcoord_index)]


@dataclass
class ObjGeometry:
    """An OBJ file's triangles in the model's layout (file units and axes; the loader converts)."""

    positions: np.ndarray  # (V, 3) float64
    normals: np.ndarray  # (V, 3) float64 (unit; triangles without normals get their geometric normal)
    uvs: np.ndarray  # (V, 2) float64, (u, 1 - v)
    faces: np.ndarray  # (F, 3) int64
    face_shape: np.ndarray  # (F,) int32, index into shape_names
    face_mtl: np.ndarray  # (F,) int32, index into materials (-1: none)
    shape_names: list[str]
    materials: list  # tinyobjloader material_t
    census: Census
    counts: dict


def read_obj(path: Path, data: bytes) -> ObjGeometry:
    """Parses ``path`` (whose bytes are ``data``) with tinyobjloader and checks it (module docstring)."""
    global _ARRAYS_OK
    try:
        import tinyobjloader
    except ImportError as exc:
        raise UserError(f"OBJ scenes need the 'tinyobjloader' package (pip install tinyobjloader): {exc}") from None
    if _ARRAYS_OK is None:
        _ARRAYS_OK = _self_test()
    cen = census(data, path)
    reader = tinyobjloader.ObjReader()
    config = tinyobjloader.ObjReaderConfig()
    config.triangulate = True
    if not reader.ParseFromFile(str(path), config):
        err = (reader.Error() or reader.Warning() or "unreadable").strip().splitlines()
        raise invalid(path, err[0] if err else "unreadable")
    warnings = [w.strip() for w in reader.Warning().splitlines() if w.strip() and w.strip() != "."]
    for w in warnings:
        if "out of bounds" in w:
            raise invalid(path, w.rstrip("."))
    attrib = reader.GetAttrib()
    shapes = reader.GetShapes()
    materials = list(reader.GetMaterials())
    verts = _array(attrib.numpy_vertices, lambda: attrib.vertices, np.float64).reshape(-1, 3)
    norms = _array(attrib.numpy_normals, lambda: attrib.normals, np.float64).reshape(-1, 3)
    texs = _array(attrib.numpy_texcoords, lambda: attrib.texcoords, np.float64).reshape(-1, 2)
    nv, nn, nt = len(verts), len(norms), len(texs)
    if nv != cen.counts.get("v", 0) or nn != cen.counts.get("vn", 0) or nt != cen.counts.get("vt", 0):
        raise invalid(path, f"read {nv} positions, {nn} normals, {nt} texture coordinates from "
                            f"{cen.counts.get('v', 0)} v, {cen.counts.get('vn', 0)} vn, {cen.counts.get('vt', 0)} vt lines")
    if not np.isfinite(verts).all():
        raise invalid(path, "a vertex position is not a finite number")

    corners, face_shape, face_mtl, names = [], [], [], []
    for s, shape in enumerate(shapes):
        mesh = shape.mesh
        idx = _array(mesh.numpy_indices, lambda m=mesh: _indices_fallback(m), np.int64)
        if idx.size % 9:
            raise invalid(path, f"shape '{shape.name}': the triangulated index list is not a whole number of "
                                f"triangles")
        idx = idx.reshape(-1, 3)
        n_tri = len(idx) // 3
        mids = _array(mesh.numpy_material_ids, lambda m=mesh: m.material_ids, np.int32)
        if len(mids) != n_tri:
            raise invalid(path, f"shape '{shape.name}': {len(mids)} material ids for {n_tri} triangles")
        corners.append(idx)
        face_shape.append(np.full(n_tri, s, np.int32))
        face_mtl.append(mids)
        names.append(shape.name or f"shape_{s}")
    if not corners or sum(len(c) for c in corners) == 0:
        raise invalid(path, "no faces")
    corner = np.concatenate(corners)  # (3F, 3): position, normal, texcoord index per corner (-1: none)
    face_shape = np.concatenate(face_shape)
    face_mtl = np.concatenate(face_mtl)
    vi, ni, ti = corner[:, 0], corner[:, 1], corner[:, 2]
    for what, ix, n in (("vertex", vi, nv), ("normal", ni, nn), ("texture coordinate", ti, nt)):
        low = 0 if what == "vertex" else -1
        if ix.min() < low or ix.max() >= n:
            bad = int(ix.max()) if ix.max() >= n else int(ix.min())
            raise invalid(path, f"a face refers to {what} {bad + 1}, the file has {n}")
    n_mat = len(materials)
    if face_mtl.max() >= n_mat or face_mtl.min() < -1:
        raise invalid(path, f"a face refers to material {int(face_mtl.max())}, the file has {n_mat}")

    counts = {"degenerate_faces_dropped_by_reader": sum(w.count("Degenerated face") for w in warnings),
              "reader_warnings": [w for w in warnings if "Degenerated face" not in w][:20]}

    # One model vertex per distinct (position, normal, texcoord) triple; corners without a normal get a vertex of
    # their own (their normal is the triangle's geometric normal).
    tri_has_normal = (ni.reshape(-1, 3) >= 0).all(axis=1)
    shared = np.repeat(tri_has_normal, 3)
    if shared.all() and nv * (nn + 1) * (nt + 1) < (1 << 62):
        key = (vi * (nn + 1) + (ni + 1)) * (nt + 1) + (ti + 1)
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        rep = corner[first]
    else:
        rows = np.where(shared[:, None], corner, np.stack([vi, -2 - np.arange(len(vi)), ti], axis=1))
        _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        rep = corner[first]
    inverse = inverse.reshape(-1)
    faces = inverse.reshape(-1, 3).astype(np.int64)
    positions = verts[rep[:, 0]]
    uvs = np.zeros((len(rep), 2))
    has_uv = rep[:, 2] >= 0
    uvs[has_uv] = texs[rep[has_uv, 2]]
    uvs[:, 1] = 1.0 - uvs[:, 1]
    normals = np.zeros((len(rep), 3))
    has_n = rep[:, 1] >= 0
    normals[has_n] = norms[rep[has_n, 1]]
    length = np.linalg.norm(normals, axis=1)
    zero_normals = int((has_n & ~(length > 0)).sum())
    tri = positions[faces]
    geo = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    geo_len = np.linalg.norm(geo, axis=1)
    geo = geo / np.maximum(geo_len, 1e-300)[:, None]
    # Vertices without a usable normal (none given, or a zero vector) take their triangle's geometric normal.
    need = ~has_n | ~(length > 0) | ~np.isfinite(length)
    if need.any():
        owner = np.zeros(len(rep), np.int64)
        owner[faces.reshape(-1)] = np.repeat(np.arange(len(faces)), 3)
        normals[need] = geo[owner[need]]
        length = np.linalg.norm(normals, axis=1)
    normals /= np.maximum(length, 1e-300)[:, None]
    counts["triangles_without_normals"] = int((~tri_has_normal).sum())
    counts["zero_normals_replaced"] = zero_normals
    counts["triangles_without_uvs"] = int(((ti.reshape(-1, 3) < 0).any(axis=1)).sum())
    return ObjGeometry(positions=positions, normals=normals, uvs=uvs, faces=faces, face_shape=face_shape,
                       face_mtl=face_mtl, shape_names=names, materials=materials, census=cen, counts=counts)
