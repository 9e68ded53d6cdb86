"""PVS light culling (seed 001 §4.3, Table 4.2): where the PVS is conservative it never changes the image (here
bit for bit: each light draws its own random numbers, so culled and unculled frames sample it identically), it
traces fewer rays, rows hold the right lights, triangles spanning clusters get merged rows, and the audit counts
the lights a wrong PVS drops."""
import numpy as np
import pytest

from methods.quake_drt import culling, lights as lights_mod
from methods.quake_drt.testscenes import BoxVisibility, ROOM_A, ROOM_B


def _light_index(prep, name):
    return prep.lights.names.index(name)


@pytest.mark.parametrize("rule", ["triangle", "point"])
def test01_closed_door_culling_changes_no_pixel_and_saves_rays(renderer, two_rooms, rule):
    scene, vis = two_rooms(door_open=False, lights_in_b=2, camera="a")
    culled = renderer(scene, vis, num_random_dl=0, cull_lights=True, pixel_cluster=rule)
    full = renderer(scene, vis, num_random_dl=0, cull_lights=False)
    img_c, raw_c = culled.raw(7)
    img_f, raw_f = full.raw(7)
    assert np.array_equal(img_c, img_f)
    assert img_f.max() > 0
    assert raw_c.info["shadow_rays"] < raw_f.info["shadow_rays"]
    assert raw_c.info["candidates"] < raw_f.info["candidates"]


def test02_rows_hold_the_lights_of_the_visible_rooms_and_door_triangles_are_merged(renderer, two_rooms):
    scene, vis = two_rooms(door_open=False, lights_in_b=2, camera="a")
    r = renderer(scene, vis, num_random_dl=0)
    t, p = r.prep.table, r.prep
    a_lights = {_light_index(p, "a_ceiling"), _light_index(p, "area_0")}
    b_lights = {_light_index(p, "b_0"), _light_index(p, "b_1")}
    assert set(t.row(0)) == a_lights and set(t.row(1)) == b_lights  # Table 4.2: cluster rows
    assert set(t.row(t.all_row)) == a_lights | b_lights
    # The door slab touches both rooms: its triangles read a merged row with both rooms' lights.
    door = scene.face_material == [m.name for m in scene.materials].index("door")
    door_rows = np.unique(t.tri_row[door])
    assert any(set(t.row(row)) == a_lights | b_lights and row not in (0, 1, t.all_row) for row in door_rows)
    # Triangles of room A's far wall read A's row only.
    far_wall = (scene.triangles()[:, :, 0] < -3.99).all(axis=1)
    assert set(np.unique(t.tri_row[far_wall])) == {0}


def test03_a_wrong_pvs_drops_a_contributing_light_and_the_audit_counts_it(renderer, two_rooms):
    """Door open, but a PVS that says the rooms cannot see each other: room B's light shines into room A through
    the doorway and culling removes it. The image differs from the unculled one and the audit reports it; with
    the right PVS it reports nothing."""
    scene, _ = two_rooms(door_open=True, lights_in_b=1, camera="a")
    wrong = BoxVisibility([ROOM_A, ROOM_B], np.eye(2, dtype=bool), scene)
    right = BoxVisibility([ROOM_A, ROOM_B], np.ones((2, 2), bool), scene)
    full_img, _ = renderer(scene, right, num_random_dl=0, cull_lights=False).raw(3)
    bad = renderer(scene, wrong, num_random_dl=0, cull_audit_points=512)
    bad_img, bad_raw = bad.raw(3)
    assert not np.array_equal(bad_img, full_img)
    audit = bad.pipeline.audit(bad.scene, bad.tracer, bad_raw, 11)
    assert audit["audit_missed"] > 0 and 0 < audit["audit_missed_energy"] < 1
    good = renderer(scene, right, num_random_dl=0, cull_audit_points=512)
    good_img, good_raw = good.raw(3)
    assert np.array_equal(good_img, full_img)
    assert good.pipeline.audit(good.scene, good.tracer, good_raw, 11)["audit_missed"] == 0


def test04_one_way_pvs_rows_are_made_symmetric_unless_asked_not_to(two_rooms):
    scene, _ = two_rooms(door_open=True, lights_in_b=1)
    one_way = np.array([[True, False], [True, True]])  # B sees A, A does not see B
    vis = BoxVisibility([ROOM_A, ROOM_B], one_way, scene)
    lights = lights_mod.build_lights(scene, 0.0)
    b = lights.names.index("b_0")
    sym = culling.build_table(vis, "scene", lights, scene.num_faces, 0.0254, symmetric=True)
    oneway = culling.build_table(vis, "scene", lights, scene.num_faces, 0.0254, symmetric=False)
    assert b in sym.row(0) and b not in oneway.row(0)


def test05_without_visibility_every_row_holds_every_light_and_the_source_says_so(renderer, two_rooms):
    scene, _ = two_rooms(door_open=False)
    r = renderer(scene, None, num_random_dl=0, pvs="none")
    t = r.prep.table
    assert t.source == "none" and t.n_rows == 1 and len(t.row(0)) == len(r.prep.lights)
    # "auto" on a scene without a BSP: a computed PVS where suite.core.scene.cellvis exists, else none.
    assert renderer(scene, None, num_random_dl=0, pvs="auto").prep.table.source in ("computed", "none")


@pytest.mark.parametrize("name", ["oa:kaos", "oa:aggressor@pak1-maps"])
def test06_on_quake_maps_culling_is_exact_and_culls(renderer, name):
    from suite.core.scene import list_scenes, load

    if list_scenes().get(name, "unavailable").startswith("unavailable"):
        pytest.skip(f"{name} needs the OpenArena data")
    scene = load(name)
    culled = renderer(scene, None, (64, 36), num_random_dl=0)
    full = renderer(scene, None, (64, 36), num_random_dl=0, cull_lights=False)
    img_c, raw_c = culled.raw(5, t_s=1.0)
    img_f, raw_f = full.raw(5, t_s=1.0)
    assert culled.prep.table.source == "bsp"
    assert np.array_equal(img_c, img_f)
    assert raw_c.info["shadow_rays"] < 0.8 * raw_f.info["shadow_rays"]
    assert culled.pipeline.audit(culled.scene, culled.tracer, raw_c, 2)["audit_missed"] == 0
