"""The distribution effects are switches (seed 001 Table 6.1, Table 2.1): off, a frame is a deterministic function of
the scene; on, it varies with the seed where the effect acts and not elsewhere: soft shadows at area-light
penumbrae, anti-aliasing at edges, depth of field away from the focal plane."""
import numpy as np
import pytest

RES = (64, 40)


@pytest.fixture
def room(two_rooms):
    return two_rooms(door_open=False, lights_in_b=0, camera="a", resolution=RES)


def _spread(r, n=6):
    stack = r.raw_stack(n)
    return stack.std(axis=0).max(axis=-1), stack.mean(axis=0)


def test01_with_every_effect_off_frames_do_not_depend_on_the_seed(renderer, room):
    scene, vis = room
    r = renderer(scene, vis, RES, num_random_dl=0, soft_shadows=False, antialiasing=False)
    spread, _ = _spread(r, 3)
    assert spread.max() == 0.0


def test02_soft_shadows_vary_only_where_an_area_light_is_partly_hidden(renderer, room):
    scene, vis = room
    soft, soft_mean = _spread(renderer(scene, vis, RES, num_random_dl=0, soft_shadows=True))
    _, hard_mean = _spread(renderer(scene, vis, RES, num_random_dl=0, soft_shadows=False), 1)
    assert 0.0 < (soft > 0).mean() < 1.0
    # the same light, sampled over its area instead of at its centre: about the same total
    assert abs(soft_mean.mean() - hard_mean.mean()) / hard_mean.mean() < 0.1


def test03_antialiasing_jitters_where_the_pixel_covers_an_edge(renderer, room):
    scene, vis = room
    r = renderer(scene, vis, RES, num_random_dl=0, soft_shadows=False, antialiasing=True)
    spread, _ = _spread(r)
    _, raw = r.raw(1)
    prim = raw.g.prim
    edge = np.zeros_like(prim, bool)
    edge[:, 1:] |= prim[:, 1:] != prim[:, :-1]
    edge[1:, :] |= prim[1:, :] != prim[:-1, :]
    assert spread[edge].mean() > 3 * spread[~edge].mean()


def test04_depth_of_field_rays_meet_at_the_focal_plane_and_spread_elsewhere(room):
    """Thin lens: every lens sample's ray of a pixel passes through the point the pinhole ray reaches at the
    focal distance, and its origin lies within the aperture; away from that plane the rays spread."""
    from methods.quake_drt.primary import camera_rays
    from methods.quake_drt.rng import pixel_seeds

    scene, _ = room
    w, h = RES
    forward = scene.camera.pose_at(0.0).basis()[0]
    pin_o, pin_d = camera_rays(scene, 0.0, w, h, pixel_seeds(1, w, h).reshape(-1), jitter=False)
    focal, aperture = 2.5, 0.05
    focus = pin_o + pin_d * (focal / (pin_d @ forward))[:, None]
    ends = []
    for seed in (1, 2, 3):
        o, d = camera_rays(scene, 0.0, w, h, pixel_seeds(seed, w, h).reshape(-1), jitter=False,
                           aperture_m=aperture, focal_m=focal)
        assert np.linalg.norm(o - pin_o, axis=1).max() <= aperture + 1e-12
        at_focus = o + d * ((focus - o) @ forward / (d @ forward))[:, None]
        assert np.abs(at_focus - focus).max() < 1e-9
        ends.append(o + d * (3 * focal / (d @ forward))[:, None])  # three times as far: out of focus
    spread = np.linalg.norm(ends[0] - ends[1], axis=1)
    assert spread.mean() > 0.5 * aperture


# Table 6.1's console commands that set a value, by the thesis's name.
THESIS_COMMANDS = {"rt_illumination": False, "rt_cullLights": False, "rt_numRandomDL": 4, "rt_antialiasing": False,
                   "rt_softshadows": False, "rt_dof": True, "rt_aperture": 0.05, "rt_focallength": 2.5,
                   "rt_denoiser": False, "rt_taa": False}


def test05_every_thesis_switch_is_a_set_under_its_own_name_and_makes_the_same_run():
    from suite.harness import registry, runner

    spec = registry.get("quake_drt")
    assert set(THESIS_COMMANDS) == set(spec.aliases)
    for command, value in THESIS_COMMANDS.items():
        name = spec.aliases[command]
        assert spec.params()[name] != value, f"{command}: pick a value that is not the default"
        by_thesis = runner.make_config("quake_drt", scene="cornell", set_values={command: value})
        by_suite = runner.make_config("quake_drt", scene="cornell", set_values={name: value})
        assert by_thesis == by_suite and by_thesis["params"][name] == value
        # Quake III's console takes its variables in any letter case
        assert runner.make_config("quake_drt", scene="cornell", set_values={command.lower(): value}) == by_suite
