"""Camera paths through Quake III maps.

Scripted paths live in ``camera_paths.toml`` (next to this file), one table per map name. A path starts at one of
the map's spawn points -- ``spawn_origin`` (its ``origin`` in Quake units, which stays valid when a later release
renumbers the spawn points) or ``spawn`` (index in entity order) -- looking along the spawn's ``angle`` plus
``yaw_deg`` (and ``pitch_deg``), at Quake III's eye height: the floor below the spawn point + 24 units (the
player box reaches 24 units below its origin) + 26 units (``DEFAULT_VIEWHEIGHT``) = 50 units = 1.27 m.
``moves`` then script the walk with :class:`~suite.core.scene.builder.CameraScript`'s vocabulary, lengths in
metres:

* ``{ walk = METRES, s = SECONDS, strafe = METRES, rise = METRES }`` (negative ``walk``: backward);
* ``{ turn = DEGREES, s = SECONDS, pitch = DEGREES, walk = METRES }`` (positive: to the left);
* ``{ hold = SECONDS }``.

Spawn points are the map's ``info_player_deathmatch`` entities, or in a map without one its
``info_player_start`` or CTF team spawn points (``convert.SPAWN_CLASSES``). A map without a script gets an
automatic path of the same shape as the embedded scenes' (walk, 90 deg turn in 0.3 s, walk, backward move,
slow pan) from its first spawn point, with every walk shortened to stay ``CLEARANCE_M`` short of the nearest
wall along it.

:func:`check_path` samples a camera path at its frame rate and reports frames whose point is in solid space
(cluster -1) and frame-to-frame segments that cross geometry.
"""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.builder import CameraScript
from suite.core.scene.model import CameraPath

PATHS_FILE = Path(__file__).with_name("camera_paths.toml")
EYE_ABOVE_FLOOR_UNITS = 24.0 + 26.0  # player box below its origin + DEFAULT_VIEWHEIGHT (bg_public.h)
VIEWHEIGHT_UNITS = 26.0
FLOOR_SEARCH_UNITS = 256.0
CLEARANCE_M = 0.5
DEFAULT_FOV_DEG = 75.0
DEFAULT_RESOLUTION = (320, 180)
DEFAULT_FPS = 30.0
FAST_TURN_DEG, FAST_TURN_S = 90.0, 0.3


def load_scripts(path: Path = PATHS_FILE) -> dict:
    try:
        return tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise UserError(f"camera paths '{path}': {exc}") from None


def ray_hits(tris: np.ndarray, origins: np.ndarray, dirs: np.ndarray, t_max=np.inf) -> np.ndarray:
    """Nearest hit distance (inf on a miss) of each ray against (F, 3, 3) triangles, brute force in float64
    (Moeller-Trumbore); for the few rays a camera path needs."""
    tri = np.asarray(tris, np.float64)
    p0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.full(len(origins), np.inf)
    t_max = np.broadcast_to(np.asarray(t_max, np.float64), (len(origins),))
    for i, (o, d) in enumerate(zip(np.asarray(origins, np.float64), np.asarray(dirs, np.float64))):
        pvec = np.cross(d, e2)
        det = np.einsum("fk,fk->f", e1, pvec)
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = o - p0
        u = np.einsum("fk,fk->f", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        v = (qvec @ d) * inv
        t = np.einsum("fk,fk->f", e2, qvec) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t <= t_max[i])
        if hit.any():
            out[i] = t[hit].min()
    return out


def spawn_eye(tris: np.ndarray, spawn_xyz: np.ndarray, unit_m: float) -> np.ndarray:
    """Eye position for a spawn point (scene coordinates): floor below + 50 units, or origin + 26 units."""
    down = ray_hits(tris, spawn_xyz[None], np.array([[0.0, -1.0, 0.0]]), FLOOR_SEARCH_UNITS * unit_m)[0]
    eye = spawn_xyz.copy()
    if np.isfinite(down):
        eye[1] = spawn_xyz[1] - down + EYE_ABOVE_FLOOR_UNITS * unit_m
    else:
        eye[1] += VIEWHEIGHT_UNITS * unit_m
    return eye


def scripted_path(name: str, script: dict, spawns: np.ndarray, tris: np.ndarray,
                  unit_m: float) -> tuple[CameraPath, str]:
    if len(spawns) == 0:
        raise UserError(f"map '{name}' has no spawn point to start its camera path from")
    if "spawn_origin" in script:
        want = np.array([float(x) for x in script["spawn_origin"]], np.float64)
        want_scene = np.array([want[0], want[2], -want[1]]) * unit_m
        dist = np.linalg.norm(spawns[:, :3] - want_scene, axis=1)
        k = int(np.argmin(dist))
        if dist[k] > unit_m:
            raise UserError(f"camera path of '{name}': no spawn point at {want.tolist()} in this map")
    else:
        k = int(script.get("spawn", 0))
        if not 0 <= k < len(spawns):
            raise UserError(f"camera path of '{name}': spawn {k} is out of range (the map has {len(spawns)})")
    eye = spawn_eye(tris, spawns[k, :3], unit_m)
    yaw = spawns[k, 3] - 90.0 + float(script.get("yaw_deg", 0.0))  # Quake angle 0 = +x; CameraScript yaw 0 = -z
    cam = CameraScript(eye, yaw_deg=yaw, pitch_deg=float(script.get("pitch_deg", 0.0)))
    cam.play(script.get("moves", []), f"camera path of '{name}',")
    path = CameraPath(keys=cam.keys, fov_deg=float(script.get("fov_deg", DEFAULT_FOV_DEG)),
                      resolution=tuple(script.get("resolution", DEFAULT_RESOLUTION)),
                      fps=float(script.get("fps", DEFAULT_FPS)))
    return path, str(script.get("description", f"scripted path from spawn point {k}"))


def _free(tris, eye, direction, unit_m) -> float:
    """Free distance (m) along a horizontal direction at eye height and at knee height (stairs, ledges)."""
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    origins = np.stack([eye, eye - np.array([0.0, 0.9, 0.0])])
    return float(ray_hits(tris, origins, np.stack([d, d]), 64.0).min())


def automatic_path(spawns: np.ndarray, tris: np.ndarray, unit_m: float) -> tuple[CameraPath, str]:
    """Walk, fast turn, walk, backward move, slow pan from the first spawn point, clipped by walls."""
    if len(spawns) == 0:
        raise UserError("the map has no spawn point (info_player_deathmatch, info_player_start, team_CTF_*) to "
                        "start a camera path from")
    eye = spawn_eye(tris, spawns[0, :3], unit_m)
    cam = CameraScript(eye, yaw_deg=spawns[0, 3] - 90.0)

    def reach(want, direction):
        free = _free(tris, cam.position, direction, unit_m) - CLEARANCE_M
        return max(0.0, min(want, free))

    cam.walk(reach(2.0, cam.heading()), 1.2)
    cam.hold(0.2)
    yaw = math.radians(cam.yaw_deg)
    left = np.array([-math.cos(yaw), 0.0, math.sin(yaw)])
    turn = FAST_TURN_DEG if _free(tris, cam.position, left, unit_m) >= _free(tris, cam.position, -left, unit_m) \
        else -FAST_TURN_DEG
    cam.turn(turn, FAST_TURN_S)
    cam.walk(reach(0.8, cam.heading()), 0.6)
    cam.walk(-reach(1.6, -cam.heading()), 1.0)
    cam.turn(-math.copysign(45.0, turn), 0.7)
    path = CameraPath(keys=cam.keys, fov_deg=DEFAULT_FOV_DEG, resolution=DEFAULT_RESOLUTION, fps=DEFAULT_FPS)
    return path, "automatic path from spawn point 0"


def make_camera(name: str, spawns: np.ndarray, tris: np.ndarray, unit_m: float) -> tuple[CameraPath, str]:
    scripts = load_scripts()
    if name.lower() in scripts:
        return scripted_path(name, scripts[name.lower()], spawns, tris, unit_m)
    return automatic_path(spawns, tris, unit_m)


def check_path(camera: CameraPath, visibility, tris: np.ndarray | None = None, step_s: float | None = None) -> dict:
    """Samples the path every frame (or ``step_s``): clusters of the camera points, and whether the segment
    between successive points crosses a triangle of ``tris`` (when given)."""
    step = step_s or 1.0 / camera.fps
    n = int(math.floor(camera.duration_s / step + 1e-9)) + 1
    times = camera.keys[0].t_s + step * np.arange(n)
    points = np.array([camera.pose_at(float(t)).position for t in times])
    clusters = visibility.cluster_of(points)
    crossings = 0
    if tris is not None and len(points) > 1:
        seg = np.diff(points, axis=0)
        length = np.linalg.norm(seg, axis=1)
        moving = length > 1e-9
        if moving.any():
            hits = ray_hits(tris, points[:-1][moving], seg[moving] / length[moving, None], length[moving])
            crossings = int(np.isfinite(hits).sum())
    return {"frames": int(n), "frames_in_solid": int((clusters < 0).sum()), "segments_crossing_geometry": crossings,
            "clusters_visited": sorted(set(int(c) for c in clusters if c >= 0)), "times_s": times,
            "clusters": clusters}
