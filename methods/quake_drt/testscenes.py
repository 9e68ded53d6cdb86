"""Small hand-made scenes with a known PVS, for the tests and the benchmark of quake_drt.

``two_rooms(door_open=False)``: rooms A (x < 0) and B (x > 0), 4 m x 2.5 m x 4 m each, separated by a 20 cm
wall with a 1 m x 2 m doorway; a door slab closes it unless ``door_open``. Room A holds a point light and an
area light on its ceiling; room B holds ``lights_in_b`` point lights (0 leaves it dark). ``extra_lights`` adds
point lights on a grid under A's ceiling (more lights than a 64-bit mask word).

:class:`BoxVisibility` gives such a scene the interface of ``scene.visibility`` (``Q3Visibility``): clusters are
axis-aligned boxes (room A, room B; -1 elsewhere, like solid in a BSP), the PVS is given (identity when the door
is closed, everything when it is open), and a triangle is in every box its bounds touch.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from suite.core.scene.builder import CameraScript, SceneBuilder
from suite.core.scene.model import CameraKey

ROOM_A = ((-4.0, 0.0, -2.0), (-0.05, 2.5, 2.0))
ROOM_B = ((0.05, 0.0, -2.0), (4.0, 2.5, 2.0))
WALL_X = 0.1  # the shared wall spans x in [-WALL_X, WALL_X]
DOOR_Z = 0.5  # the doorway spans z in [-DOOR_Z, DOOR_Z], y in [0, DOOR_H]
DOOR_H = 2.0


class BoxVisibility:
    """Clusters as boxes with a given PVS; the subset of ``Q3Visibility``'s interface the methods read."""

    def __init__(self, boxes, pvs: np.ndarray, scene, eps: float = 1e-3):
        self.boxes = [(np.asarray(lo, np.float64), np.asarray(hi, np.float64)) for lo, hi in boxes]
        self._pvs = np.asarray(pvs, bool)
        self.n_clusters = len(self.boxes)
        self.has_vis = True
        tri = scene.triangles().astype(np.float64)
        tmin, tmax = tri.min(axis=1), tri.max(axis=1)
        member = np.stack([((tmin <= hi + eps) & (tmax >= lo - eps)).all(axis=1) for lo, hi in self.boxes], axis=1)
        rows, cl = np.nonzero(member)
        self.triangle_cluster_offsets = np.searchsorted(rows, np.arange(len(tri) + 1)).astype(np.int64)
        self.triangle_cluster_ids = cl.astype(np.int32)
        first = np.full(len(tri), -1, np.int32)
        has = member.any(axis=1)
        first[has] = member[has].argmax(axis=1)
        self.triangle_cluster = first

    @property
    def leaf_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(C, 3) min and max corners: every box is one leaf of its own cluster."""
        return np.array([lo for lo, _ in self.boxes]), np.array([hi for _, hi in self.boxes])

    @property
    def leaf_cluster(self) -> np.ndarray:
        return np.arange(self.n_clusters, dtype=np.int32)

    def cluster_of(self, points) -> np.ndarray:
        p = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.full(len(p), -1, np.int64)
        for c, (lo, hi) in enumerate(self.boxes):
            inside = ((p >= lo) & (p <= hi)).all(axis=1) & (out < 0)
            out[inside] = c
        return out

    def pvs(self, cluster: int) -> np.ndarray:
        return self._pvs[int(cluster)].copy() if cluster >= 0 else np.zeros(self.n_clusters, bool)

    def pvs_matrix(self) -> np.ndarray:
        return self._pvs.copy()

    def clusters_of_triangle(self, i: int) -> np.ndarray:
        return self.triangle_cluster_ids[self.triangle_cluster_offsets[i]:self.triangle_cluster_offsets[i + 1]]


def _room_walls(b, lo, hi, mat, door_side: str):
    """An inward box without the face toward the door wall, and that face with a doorway cut out."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    x_wall = hi[0] if door_side == "+x" else lo[0]
    b.add_box(lo, hi, mat, open_faces=(door_side,), inward=True)
    facing = np.array([-1.0 if door_side == "+x" else 1.0, 0.0, 0.0])
    y0, y1, z0, z1 = lo[1], hi[1], lo[2], hi[2]
    quads = [[(x_wall, y0, z0), (x_wall, y0, -DOOR_Z), (x_wall, y1, -DOOR_Z), (x_wall, y1, z0)],
             [(x_wall, y0, DOOR_Z), (x_wall, y0, z1), (x_wall, y1, z1), (x_wall, y1, DOOR_Z)],
             [(x_wall, DOOR_H, -DOOR_Z), (x_wall, DOOR_H, DOOR_Z), (x_wall, y1, DOOR_Z), (x_wall, y1, -DOOR_Z)]]
    b.add_quads(np.array(quads), mat, facing=facing)


def two_rooms(door_open: bool = False, lights_in_b: int = 1, extra_lights: int = 0, area_light: bool = True,
              camera: str = "a", resolution=(48, 32)):
    """The two-room scene and its :class:`BoxVisibility` (module docstring). ``camera``: "a" looks from room A
    toward the door, "b" from room B toward the door, "b_away" from room B at its far wall."""
    b = SceneBuilder()
    wall = b.add_material("wall", albedo=(0.6, 0.55, 0.5))
    door = b.add_material("door", albedo=(0.4, 0.3, 0.2))
    block = b.add_material("block", albedo=(0.3, 0.5, 0.35))
    lo_a, hi_a = (-4.0, 0.0, -2.0), (-WALL_X, 2.5, 2.0)
    lo_b, hi_b = (WALL_X, 0.0, -2.0), (4.0, 2.5, 2.0)
    _room_walls(b, lo_a, hi_a, wall, "+x")
    _room_walls(b, lo_b, hi_b, wall, "-x")
    # The doorway's reveals (inside the wall's thickness), facing into the opening.
    x0, x1 = -WALL_X, WALL_X
    b.add_quads(np.array([[(x0, 0, -DOOR_Z), (x1, 0, -DOOR_Z), (x1, DOOR_H, -DOOR_Z), (x0, DOOR_H, -DOOR_Z)],
                          [(x0, 0, DOOR_Z), (x0, DOOR_H, DOOR_Z), (x1, DOOR_H, DOOR_Z), (x1, 0, DOOR_Z)],
                          [(x0, DOOR_H, -DOOR_Z), (x1, DOOR_H, -DOOR_Z), (x1, DOOR_H, DOOR_Z),
                           (x0, DOOR_H, DOOR_Z)]]),
                wall, facing=np.array([[0, 0, 1.0], [0, 0, -1.0], [0, -1.0, 0]]))
    if not door_open:
        b.add_box((-0.05, 0.0, -DOOR_Z), (0.05, DOOR_H, DOOR_Z), door)
    b.add_box((-2.6, 0.0, -0.6), (-1.8, 0.9, 0.2), block)  # casts shadows in room A
    b.add_box((1.6, 0.0, 0.6), (2.2, 0.7, 1.3), block)  # and in room B
    b.add_point_light("a_ceiling", (-2.0, 2.2, 0.8), intensity=(6.0, 5.5, 5.0))
    if area_light:
        b.add_area_light_quad("a_panel", (-3.0, 2.45, -1.0), (0.8, 0.6), (0.0, -1.0, 0.0), radiance=(12.0, 11.0, 10.0))
    for i in range(lights_in_b):
        b.add_point_light(f"b_{i}", (2.0 + 0.5 * i, 2.1, -0.8 + 0.4 * i), intensity=(4.0, 4.5, 5.0))
    if extra_lights:
        nx = int(np.ceil(np.sqrt(extra_lights)))
        for i in range(extra_lights):
            gx, gz = divmod(i, nx)
            b.add_point_light(f"a_grid_{i}", (-3.8 + 3.5 * (gx + 0.5) / nx, 2.3, -1.8 + 3.6 * (gz + 0.5) / nx),
                              intensity=0.08)
    views = {"a": ((-3.5, 1.4, 1.5), -60.0), "b": ((3.5, 1.4, 1.5), 60.0), "b_away": ((0.8, 1.4, 0.0), -90.0)}
    pos, yaw = views[camera]
    cam = CameraScript(pos, yaw_deg=yaw, pitch_deg=-10.0)
    cam.hold(1.0)
    b.set_camera(cam.keys, fov_deg=75.0, resolution=resolution)
    scene = b.build("two_rooms_open" if door_open else "two_rooms", "two rooms joined by a doorway")
    pvs = np.ones((2, 2), bool) if door_open else np.eye(2, dtype=bool)
    return scene, BoxVisibility([ROOM_A, ROOM_B], pvs, scene)


def with_visibility(scene, vis):
    """A copy of ``scene`` that carries ``vis`` as ``scene.visibility`` (duck-typed, as Q3Scene does)."""
    out = dataclasses.replace(scene)
    out.visibility = vis
    return out


def still_camera(scene, position, target):
    """A copy of ``scene`` whose camera stands still at ``position`` looking at ``target``."""
    cam = dataclasses.replace(scene.camera, keys=[CameraKey(0.0, position, target)])
    return dataclasses.replace(scene, camera=cam)


def switch_off(scene, name: str, frame: int, fps: float = 30.0) -> None:
    """Makes ``scene.lights_at`` return light ``name`` with zero intensity from frame ``frame`` on (at ``fps``): a
    light switched off, for the denoiser's anti-lag."""
    original = scene.lights_at

    def lights_at(t_s):
        lights = original(t_s)
        if t_s >= frame / fps - 1e-9:
            lights = [dataclasses.replace(lt, intensity=np.zeros(3, np.float32)) if lt.name == name else lt
                      for lt in lights]
        return lights

    scene.lights_at = lights_at
