"""Emissive triangles as area lights: the model's per-triangle light list, and a light made of many small
triangles (what a Quake III surface-light loader produces) lighting a scene like one big one, here and in Mitsuba."""
import numpy as np
import pytest

from suite.core.gbuffer import render_gbuffer
from suite.core.reference import render_with_stderr
from suite.core.scene import load
from suite.core.scene.builder import SceneBuilder
from suite.core.scene.mitsuba_io import to_mitsuba_dict
from suite.core.scene.model import CameraKey
from suite.core.shading import AreaLights, direct_lighting
from suite.core.specular import render_materials
from suite.core.trace import backend_params, make


def test01_light_list_describes_every_emissive_triangle():
    scene = load("atrium")
    lights = scene.area_light_triangles(0.5)
    np.testing.assert_array_equal(lights.faces, scene.emissive_faces())
    assert len(lights) == len(scene.emissive_faces()) > 0
    np.testing.assert_allclose(np.linalg.norm(lights.normal, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(lights.area, scene.face_areas()[lights.faces], rtol=1e-6)
    for row, face in enumerate(lights.faces):
        np.testing.assert_array_equal(lights.radiance[row], scene.materials[scene.face_material[face]].emission)
    # The emitting side is the side the mesh's vertex normals point to.
    assert (np.einsum("ij,ij->i", lights.normal, scene.normals[scene.faces[lights.faces, 0]]) > 0).all()
    np.testing.assert_allclose(lights.power, np.pi * lights.area * lights.radiance.mean(axis=1))
    # The direct-lighting kernels sample exactly this list.
    area = AreaLights(scene, 0.5)
    np.testing.assert_array_equal(area.area, lights.area)
    np.testing.assert_array_equal(area.normal, lights.normal)


def lit_floor(subdivisions: int, res=(32, 24)):
    """A floor under a 1 x 1 m emissive panel facing down, made of 2 * subdivisions^2 triangles."""
    b = SceneBuilder()
    floor = b.add_material("floor", albedo=0.6)
    b.add_quad(((0, 0, 0), (0, 0, 3), (3, 0, 0)), floor)
    panel = b.add_material("panel", albedo=0.0, emission=(5.0, 4.5, 4.0))
    n = subdivisions
    s = np.linspace(-0.5, 0.5, n + 1)
    xx, zz = np.meshgrid(s, s, indexing="ij")
    pos = np.stack([xx.ravel(), np.full(xx.size, 1.5), zz.ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b_, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b_, c], 1), np.stack([a, c, d], 1)])
    tri = pos[faces]
    if np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])[1] > 0:
        faces = faces[:, ::-1]  # wind the panel to face down
    b.add_mesh(pos, np.tile([0.0, -1.0, 0.0], (len(pos), 1)), np.zeros((len(pos), 2)), faces, panel)
    b.set_camera([CameraKey(0.0, (0, 1.2, 3.0), (0, 0, 0))], fov_deg=60, resolution=res)
    return b.build(f"panel_{n}")


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test02_many_small_emissive_triangles_light_like_one_panel(backend):
    one, many = lit_floor(1), lit_floor(12)
    assert len(one.area_light_triangles()) == 2 and len(many.area_light_triangles()) == 288
    np.testing.assert_allclose(many.area_light_triangles().power.sum(), one.area_light_triangles().power.sum())
    means = []
    for scene in (one, many):
        tracer = make(backend, scene)
        g = render_gbuffer(scene, tracer, 0.0)
        runs = np.stack([direct_lighting(scene, g, tracer, 0.0, area_samples=16, seed=s) for s in range(4)])
        floor = g.valid & (g.position[..., 1] < 0.5)
        means.append((runs[:, floor].mean(), runs[:, floor].mean(axis=(1, 2)).std(ddof=1) / 2))
    (m1, s1), (m2, s2) = means
    assert abs(m1 - m2) < 5 * np.hypot(s1, s2) + 1e-3 * m1


def test03_many_small_triangles_match_mitsuba():
    """The subdivided panel exported to Mitsuba (one mesh with an area emitter) and rendered by `direct` agrees
    with our kernels (floor pixels, mean over the image within 1 %)."""
    scene = lit_floor(12)
    tracer = make("embree", scene)
    ours = render_materials(scene, tracer, 0.0, area_samples=64, seed=3)
    ref, _ = render_with_stderr(to_mitsuba_dict(scene, 0.0, scene.camera.resolution, integrator={"type": "direct"}),
                                spp=512, passes=8, seed=1)
    g = ours.gbuffer
    floor = g.valid & (g.position[..., 1] < 0.5)
    assert ours.image[floor].mean() == pytest.approx(ref[floor].mean(), rel=0.01)
    panel = g.valid & (g.position[..., 1] > 1.0)
    if panel.any():  # seen from below it emits: emission is in both images
        assert ours.image[panel].mean() == pytest.approx(ref[panel].mean(), rel=0.02)
