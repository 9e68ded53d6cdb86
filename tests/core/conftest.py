"""Small synthetic scenes for the core tests, built directly on the scene model."""
import numpy as np
import pytest

from suite.core.scene.model import CameraKey, CameraPath, Material, PointLight, Scene


def quad_mesh(corners, normal):
    pos = np.asarray(corners, np.float32)
    nrm = np.tile(np.asarray(normal, np.float32), (4, 1))
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return pos, nrm, uv, faces


def box_mesh(lo, hi, inward=False):
    """Closed axis-aligned box; 12 triangles, outward (or inward) normals, unshared vertices per side."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    parts = []
    for axis in range(3):
        for side, coord in ((-1, lo[axis]), (1, hi[axis])):
            a, b = (axis + 1) % 3, (axis + 2) % 3
            corners = []
            for ca, cb in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.zeros(3)
                p[axis] = coord
                p[a] = (lo[a], hi[a])[ca]
                p[b] = (lo[b], hi[b])[cb]
                corners.append(p)
            n = np.zeros(3)
            n[axis] = side * (-1 if inward else 1)
            pos, nrm, uv, faces = quad_mesh(corners, n)
            # Wind counter-clockwise around the stored normal.
            gn = np.cross(pos[1] - pos[0], pos[2] - pos[0])
            if np.dot(gn, n) < 0:
                faces = faces[:, ::-1]
            parts.append((pos, nrm, uv, faces))
    return merge(parts)


def merge(parts):
    pos, nrm, uv, faces, base = [], [], [], [], 0
    for p, n, u, f in parts:
        pos.append(p), nrm.append(n), uv.append(u), faces.append(f + base)
        base += len(p)
    return np.concatenate(pos), np.concatenate(nrm), np.concatenate(uv), np.concatenate(faces)


def make_scene(parts_with_material, materials, lights, eye, target, resolution=(48, 32), fov_deg=60.0, name="test"):
    pos, nrm, uv, faces, mats, objs, base = [], [], [], [], [], [], 0
    for obj, ((p, n, u, f), mat) in enumerate(parts_with_material):
        pos.append(p), nrm.append(n), uv.append(u), faces.append(f + base)
        mats.append(np.full(len(f), mat)), objs.append(np.full(len(f), obj))
        base += len(p)
    cam = CameraPath([CameraKey(0.0, eye, target)], fov_deg=fov_deg, resolution=resolution)
    return Scene(name, np.concatenate(pos), np.concatenate(nrm), np.concatenate(uv), np.concatenate(faces),
                 np.concatenate(mats), np.concatenate(objs), [f"o{i}" for i in range(len(parts_with_material))],
                 materials, lights, cam)


@pytest.fixture
def grazing_plane_scene():
    """A 40 m floor lit by a point light at 85 degrees from the normal over the viewed region."""
    floor = quad_mesh([[-20, 0, -20], [-20, 0, 20], [20, 0, 20], [20, 0, -20]], [0, 1, 0])
    theta = np.radians(85.0)
    light = PointLight("grazing", [30 * np.sin(theta), 30 * np.cos(theta), 0.0], [500.0] * 3)
    return make_scene([(floor, 0)], [Material("grey", [0.5] * 3)], [light], eye=[0, 3, 6], target=[0, 0, 0])


@pytest.fixture
def room_scene():
    """A closed room with two blocks and three point lights (one of them shadowed from part of the floor)."""
    room = box_mesh([-3, 0, -3], [3, 2.5, 3], inward=True)
    block_a = box_mesh([-1.5, 0, -1], [-0.5, 1.2, 0])
    block_b = box_mesh([0.5, 0, 0.5], [1.8, 0.6, 1.5])
    lights = [PointLight("a", [0, 2.2, 0], [4.0, 3.5, 3.0]), PointLight("b", [-2.5, 1.5, 2.5], [2.0, 2.0, 2.5]),
              PointLight("c", [2.5, 2.0, -2.5], [1.5, 1.0, 1.0])]
    mats = [Material("wall", [0.7, 0.5, 0.5]), Material("block", [0.3, 0.6, 0.4])]
    return make_scene([(room, 0), (block_a, 1), (block_b, 1)], mats, lights, eye=[0, 1.6, 2.8], target=[0, 0.6, 0])
