"""Transparent overlays along the primary ray (seed 001 §6.4, Algorithm 6.1): ADD and ALPHA surfaces marked by
the scene's per-face flags blend front to back in the right order whatever their number (the thesis's
any-hit shader could order only two), they cast no shadows, and pixels without them are unchanged."""
import types

import numpy as np
import pytest

from suite.core.scene.builder import SceneBuilder
from suite.core.scene.model import CameraKey
from suite.core.scene.q3 import FLAGS

RES = (40, 30)
LAYERS = [  # (z of the quad, colour, blend) front (largest z, nearest the camera) to back
    (1.0, (0.8, 0.1, 0.1), "alpha"),
    (0.5, (0.1, 0.6, 0.1), "add"),
    (0.0, (0.1, 0.1, 0.9), "alpha"),
    (-0.5, (0.5, 0.5, 0.0), "alpha"),
]


def _scene(order, with_overlays=True):
    b = SceneBuilder()
    wall = b.add_material("wall", albedo=(0.6, 0.6, 0.6))
    b.add_quad(((0, 0, -2.0), (3.0, 0, 0), (0, 3.0, 0)), wall)
    flags = [0, 0]
    if with_overlays:
        for i in order:
            z, colour, blend = LAYERS[i]
            m = b.add_material(f"layer{i}", albedo=colour)
            b.add_quad(((0, 0, z), (0.5, 0, 0), (0, 0.5, 0)), m)
            flags += [FLAGS["blend_add"] if blend == "add" else FLAGS["blend_blend"]] * 2
    # a light in front of everything, so that the overlays lie between it and the wall
    b.add_point_light("front", (0.0, 0.0, 3.0), intensity=20.0)
    b.set_camera([CameraKey(0.0, (0.0, 0.0, 5.0), (0.0, 0.0, 0.0))], fov_deg=30.0, resolution=RES)
    scene = b.build("overlays")
    # Duck-typed Quake III records: one "BSP face" per triangle with its flags (docs/scenes.md, Shaders).
    scene.q3 = types.SimpleNamespace(face_flags=np.array(flags, np.int64), triangle_face=np.arange(len(flags)))
    return scene


def _expected(shaded):
    acc, t = np.zeros(3), 1.0
    for _, colour, blend in LAYERS:
        if blend == "add":
            acc = acc + t * np.asarray(colour)
        else:
            acc = acc + t * 0.5 * np.asarray(colour)
            t *= 0.5
    return acc + t * shaded


@pytest.mark.parametrize("order", [(0, 1, 2, 3), (3, 1, 0, 2), (2, 3, 1, 0)])
def test01_four_layers_blend_in_depth_order_whatever_the_triangle_order(renderer, order):
    plain, _ = renderer(_scene(order, with_overlays=False), None, RES, num_random_dl=0, pvs="none").raw(1)
    img, raw = renderer(_scene(order), None, RES, num_random_dl=0, pvs="none", overlay_alpha=0.5).raw(1)
    c = (RES[1] // 2, RES[0] // 2)
    assert raw.info["overlay_pixels"] > 0
    # the overlays cast no shadow: the wall behind them is lit as without them
    assert np.allclose(img[c], _expected(plain[c]), rtol=1e-5)
    corner = (2, 2)  # outside the overlays: unchanged
    assert np.array_equal(img[corner], plain[corner])


def test02_transparency_scene_mode_keeps_them_opaque(renderer):
    img, raw = renderer(_scene((0, 1, 2, 3)), None, RES, num_random_dl=0, pvs="none", transparency="scene").raw(1)
    c = (RES[1] // 2, RES[0] // 2)
    assert raw.info["overlay_pixels"] == 0
    assert img[c][0] > img[c][2]  # the red front quad, lit


@pytest.mark.parametrize("antialiasing", [False, True])
def test03_the_gbuffer_guides_show_the_opaque_surface_behind_the_overlays(renderer, antialiasing):
    _, raw = renderer(_scene((0, 1, 2, 3)), None, RES, num_random_dl=0, pvs="none",
                      antialiasing=antialiasing).raw(1)
    c = (RES[1] // 2, RES[0] // 2)
    assert raw.g.prim[c] in (0, 1)  # the wall's two triangles, not an overlay quad's
    assert raw.g.depth[c] == pytest.approx(7.0, rel=1e-4)  # camera at z = 5, wall at z = -2
