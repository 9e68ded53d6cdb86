"""Hard cases of the renderer: a light sunk into a wall, a light exactly on a surface, grazing shadow rays, a
pixel whose cluster sees no light, more lights than a 64-bit mask word, k larger than the culled light count,
and a paused camera whose history length reaches its cap without drift."""
import dataclasses

import numpy as np

from methods.quake_drt import testscenes
from suite.core.scene.model import PointLight


def _with_light(scene, name, position, intensity=5.0):
    lights = list(scene.point_lights) + [PointLight(name, position, [intensity] * 3)]
    return dataclasses.replace(scene, point_lights=lights)


def _visibility(scene, door_open=False):
    pvs = np.ones((2, 2), bool) if door_open else np.eye(2, dtype=bool)
    return testscenes.BoxVisibility([testscenes.ROOM_A, testscenes.ROOM_B], pvs, scene)


def test01_a_light_sunk_into_a_wall_gets_the_clusters_around_it(renderer, two_rooms):
    scene, _ = two_rooms(lights_in_b=1, camera="a")
    # 1 cm inside room A's far wall (x = -4): in solid, cluster -1 for the point lookup.
    scene = _with_light(scene, "sunk", (-4.01, 1.2, 0.0))
    vis = _visibility(scene)
    assert vis.cluster_of(np.array([[-4.01, 1.2, 0.0]]))[0] == -1
    culled = renderer(scene, vis, num_random_dl=0)
    li = culled.prep.lights.names.index("sunk")
    t = culled.prep.table
    assert not t.light_unclustered[li] and li in t.row(0) and li not in t.row(1)
    img_c, _ = culled.raw(2)
    img_f, _ = renderer(scene, vis, num_random_dl=0, cull_lights=False).raw(2)
    assert np.isfinite(img_c).all() and np.array_equal(img_c, img_f)


def test02_a_light_exactly_on_the_floor_stays_finite_and_lights_the_walls(renderer, two_rooms):
    scene, _ = two_rooms(lights_in_b=0, area_light=False, camera="a")
    scene = dataclasses.replace(scene, point_lights=[PointLight("on_floor", (-2.0, 0.0, 0.5), [3.0] * 3)])
    vis = _visibility(scene)
    img, raw = renderer(scene, vis, num_random_dl=0).raw(1)
    assert np.isfinite(img).all() and (img >= 0).all() and img.max() > 0
    assert np.array_equal(img, renderer(scene, vis, num_random_dl=0, cull_lights=False).raw(1)[0])


def test03_grazing_shadow_rays_leave_no_acne(renderer):
    """A 40 m floor lit 85 degrees from its normal by a point light and an area light: nothing can shadow it,
    so every floor pixel must be lit by both (robust ray origins, no self-intersection)."""
    from suite.core.scene.builder import SceneBuilder
    from suite.core.scene.model import CameraKey

    b = SceneBuilder()
    grey = b.add_material("grey", albedo=0.5)
    b.add_quad(((0.0, 0.0, 0.0), (20.0, 0.0, 0.0), (0.0, 0.0, -20.0)), grey)
    theta = np.radians(85.0)
    b.add_point_light("grazing", (30 * np.sin(theta), 30 * np.cos(theta), 0.0), intensity=500.0)
    b.add_area_light_quad("low_panel", (-30 * np.sin(theta), 30 * np.cos(theta), 0.0), (2.0, 2.0),
                          (np.sin(theta), -np.cos(theta), 0.0), radiance=50.0)
    b.set_camera([CameraKey(0.0, (0.0, 3.0, 6.0), (0.0, 0.0, 0.0))], fov_deg=60.0, resolution=(64, 40))
    scene = b.build("grazing_floor")
    r = renderer(scene, None, (64, 40), num_random_dl=0, pvs="none")
    _, raw = r.raw(1)
    pts = raw.info["points"]
    assert len(pts) > 1000
    assert raw.info["shadow_rays"] == 2 * len(pts)  # every point faces both lights
    assert raw.info["shadow_rays_visible"] == raw.info["shadow_rays"], "shadow acne"


def test04_a_pixel_whose_cluster_sees_no_light_is_black_and_traces_nothing(renderer, two_rooms):
    scene, vis = two_rooms(door_open=False, lights_in_b=0, camera="b_away")
    for k in (0, 1):
        r = renderer(scene, vis, num_random_dl=k)
        assert len(r.prep.table.row(1)) == 0  # room B's row is empty (Table 4.2: count 0)
        img, raw = r.raw(4)
        assert raw.info["shadow_rays"] == 0 and raw.info["candidates"] == 0
        assert np.isfinite(img).all() and img.max() == 0.0
    img_f, raw_f = renderer(scene, vis, num_random_dl=0, cull_lights=False).raw(4)
    assert img_f.max() == 0.0 and raw_f.info["candidates"] > 0  # unculled: rays to room A's lights, all blocked


def test05_more_lights_than_a_mask_word(renderer, two_rooms):
    scene, vis = two_rooms(door_open=False, lights_in_b=1, extra_lights=100, camera="a")
    r = renderer(scene, vis, num_random_dl=0)
    n = len(r.prep.lights)
    assert n > 100 and max(r.prep.table.row(0)) > 64
    img, raw = r.raw(3)
    assert np.array_equal(img, renderer(scene, vis, num_random_dl=0, cull_lights=False).raw(3)[0])
    # The lights past index 64 do contribute: without them the image is darker.
    last = [lt.name for lt in scene.point_lights][-1]
    dim = dataclasses.replace(scene, point_lights=[lt if lt.name != last else PointLight(last, lt.position, [0.0] * 3)
                                                   for lt in scene.point_lights])
    img_dim, _ = renderer(dim, _visibility(dim), num_random_dl=0).raw(3)
    assert img_dim.sum() < img.sum()
    # One light of 100+ per pixel is still unbiased (image mean within 4.5 standard errors of the mean).
    stack = renderer(scene, vis, num_random_dl=1).raw_stack(64)
    means = stack.reshape(len(stack), -1).mean(axis=1)
    assert abs(means.mean() - img.mean()) < 4.5 * means.std(ddof=1) / np.sqrt(len(means))


def test06_k_larger_than_the_culled_light_count_uses_them_all(renderer, two_rooms):
    scene, vis = two_rooms(door_open=False, lights_in_b=2, camera="a")
    all_img, _ = renderer(scene, vis, num_random_dl=0).raw(9)
    big_img, raw = renderer(scene, vis, num_random_dl=16).raw(9)
    assert max(renderer(scene, vis).prep.table.row_counts()) < 16
    assert np.array_equal(all_img, big_img)
    assert raw.info["selected"] == raw.info["candidates"]


def test07_a_paused_camera_reaches_the_history_cap_without_drift(renderer, two_rooms):
    scene, vis = two_rooms(door_open=False, lights_in_b=1, camera="a")
    cap = 6
    r = renderer(scene, vis, num_random_dl=1, denoiser=True, taa=True, asvgf_history_cap=cap)
    hist, means = [], []
    r.frames(16, each=lambda i, img, den, raw, rec: (hist.append(rec["hist_len_max"]), means.append(img.mean())))
    assert hist[:cap] == [float(i + 1) for i in range(cap)] and all(h == cap for h in hist[cap:])
    ref = renderer(scene, vis, num_random_dl=0).raw_stack(8).mean()
    late = np.array(means[8:])
    assert abs(late[-1] - late[0]) / ref < 0.02  # no drift once the history is full
    assert abs(late.mean() - ref) / ref < 0.03  # and no energy lost or gained
