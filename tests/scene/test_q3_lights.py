"""Light conversions from q3map2's conventions to W/sr and W/m^2/sr, on synthetic entities and shaders."""
import math

import numpy as np

from suite.core.scene.q3 import lights as L
from suite.core.scene.q3.shaders import ShaderInfo, Stage, parse_shader_text

UNIT_M = 0.0254
W_SR_PER_LIGHT = 7500 * math.pi / 63.75 * UNIT_M ** 2  # 0.2385 W/sr per unit of `light`


def convert(*entities, unit_m=UNIT_M, scale=1.0):
    return L.convert_light_entities(list(entities), unit_m, scale)


def test01_point_light_intensity_and_defaults():
    (a, b, c, d), skipped = convert({"classname": "light", "origin": "0 0 0"},
                                    {"classname": "light", "light": "200", "_light": "400"},
                                    {"classname": "light", "light": "200", "scale": "2"},
                                    {"classname": "light", "light": "150"})
    assert skipped == {}
    assert math.isclose(a.intensity_w_sr, 300 * W_SR_PER_LIGHT, rel_tol=1e-12)  # q3map2's default 300
    assert math.isclose(b.intensity_w_sr, 400 * W_SR_PER_LIGHT, rel_tol=1e-12)  # _light before light
    assert math.isclose(c.intensity_w_sr, 400 * W_SR_PER_LIGHT, rel_tol=1e-12)  # scale multiplies
    assert math.isclose(d.intensity_w_sr, 150 * W_SR_PER_LIGHT, rel_tol=1e-12)
    assert math.isclose(W_SR_PER_LIGHT, 0.23845, rel_tol=1e-4)


def test02_irradiance_matches_q3map2_luxels_in_any_unit():
    """q3map2: luxel = light * 7500 * cos / d^2 (d in units); we: E = I cos / d_m^2 with E = luxel * pi / 63.75.
    Same at every distance and for any metres-per-unit scale."""
    for unit_m in (0.0254, 0.03125, 1.0):
        (lt,), _ = convert({"classname": "light", "light": "250"}, unit_m=unit_m)
        for d_units in (16.0, 100.0, 1000.0):
            luxel = 250 * 7500 / d_units ** 2
            e = lt.intensity_w_sr / (d_units * unit_m) ** 2
            assert math.isclose(e, luxel * math.pi / 63.75, rel_tol=1e-12)


def test03_colour_is_normalised_and_decoded():
    (lt,), _ = convert({"classname": "light", "_color": "0.5 0.25 0"})
    assert np.allclose(lt.color, [1.0, L.srgb_to_linear(0.5), 0.0])
    (white,), _ = convert({"classname": "light", "_color": "0 0 0"})  # ColorNormalize of black is white
    assert np.allclose(white.color, 1.0)
    assert np.allclose(lt.rgb_w_sr, lt.color * lt.intensity_w_sr)


def test04_linear_falloff_equivalent():
    (lt,), _ = convert({"classname": "light", "light": "400", "spawnflags": "1"})
    assert lt.kind == "linear"
    reach = 400 * 7500 / 8000  # luxel value at distance 0; it falls by 1 per unit and reaches 0 here
    assert math.isclose(lt.extra["linear_reach_units"], reach)
    # Equal to q3map2's linear luxel value at half the reach.
    d = reach / 2
    luxel_linear = 400 * 7500 / 8000 - d
    e = lt.intensity_w_sr / (d * UNIT_M) ** 2
    assert math.isclose(e, luxel_linear * math.pi / 63.75, rel_tol=1e-12)


def test05_spot_lights():
    ents = [{"classname": "light", "origin": "0 0 256", "target": "t1", "light": "280"},
            {"classname": "info_null", "targetname": "t1", "origin": "0 0 56"},
            {"classname": "light", "origin": "0 0 256", "target": "t2", "radius": "100"},
            {"classname": "info_null", "targetname": "t2", "origin": "0 300 256"},
            {"classname": "light", "origin": "0 0 0", "target": "nowhere"}]
    (spot, spot2, point), skipped = convert(*ents)
    assert spot.kind == "spot" and math.isclose(spot.intensity_w_sr, 280 * W_SR_PER_LIGHT)
    assert np.allclose(spot.spot_direction_q3, [0, 0, -1])
    assert math.isclose(spot.spot_half_angle_deg, math.degrees(math.atan((64 + 16) / 200)))
    assert math.isclose(spot2.spot_half_angle_deg, math.degrees(math.atan((100 + 16) / 300)))
    rec = spot.record(lambda q: np.asarray(q) * UNIT_M)
    assert np.allclose(rec["spot_direction"], [0, -1, 0])  # Quake -z is scene -y
    assert point.kind == "point" and skipped == {}  # a missing target leaves a point light (q3map2 warns)


def test06_skipped_lights_are_counted():
    ents = [{"classname": "light", "origin": "0 0 0", "target": "s", "_sun": "1"},
            {"classname": "info_null", "targetname": "s", "origin": "0 0 -10"},
            {"classname": "lightJunior", "light": "100"},
            {"classname": "light", "light": "-200"},
            {"classname": "light", "noradiosity": "1"},
            {"classname": "func_door"}]
    lights, skipped = convert(*ents)
    assert lights == []
    assert skipped == {"_sun spot (directional sun)": 1, "lightJunior (light grid only)": 1, "negative light": 1,
                       "noradiosity": 1}


def test07_surface_light_radiance():
    """Luxel = F * V * 3 * 0.25 for a form factor F; a Lambertian emitter of radiance L gives E = pi L F, so
    L = 0.75 V / 63.75."""
    assert math.isclose(L.surface_radiance(1000.0), 1000 * 0.75 / 63.75)
    assert math.isclose(L.surface_radiance(1000.0, light_scale=2.0), 2 * 1000 * 0.75 / 63.75)
    F = 0.1
    assert math.isclose(math.pi * L.surface_radiance(400.0) * F, F * 400 * 0.75 * math.pi / 63.75)


def test08_sun_and_sky_dome():
    pos, d, rgb = L.sun_light((1, 1, 1), 150.0, 90.0, 30.0, np.zeros(3))
    # Quake direction (cos a cos e, sin a cos e, sin e) = (0, 0.866, 0.5) -> scene (0, 0.5, -0.866).
    assert np.allclose(d, [0, 0.5, -math.sqrt(3) / 2])
    assert np.allclose(np.linalg.norm(pos), L.SUN_DISTANCE_M)
    assert np.allclose(rgb / L.SUN_DISTANCE_M ** 2, 150 * math.pi / 63.75)  # irradiance at normal incidence
    radiance = np.array([0.5, 0.6, 0.7])
    pos, dirs, rgb = L.sky_dome_lights(radiance, np.array([1.0, 2.0, 3.0]))
    assert len(dirs) == L.SKY_DOME_BANDS * L.SKY_DOME_AZIMUTHS and (dirs[:, 1] > 0).all()
    # A horizontal surface under the whole dome receives pi * L, what a uniform sky of radiance L gives.
    e = (rgb / L.SUN_DISTANCE_M ** 2 * dirs[:, 1:2]).sum(axis=0)
    assert np.allclose(e, math.pi * radiance)


def test09_shader_properties():
    text = """
    textures/x/lamp
    {
        qer_editorimage textures/x/lamp_ed.tga
        q3map_lightimage textures/x/lamp_glow.tga
        q3map_surfacelight 2500
        surfaceparm nomarks
        { map $lightmap }
        { map textures/x/lamp.tga
          blendFunc GL_DST_COLOR GL_ZERO }
        { map textures/x/lamp_glow.tga
          blendfunc add }
    }
    textures/x/grate { surfaceparm trans
        cull none
        { map textures/x/grate.tga
          alphaFunc GE128 } }
    textures/x/beam { { map textures/x/beam.tga
          blendFunc GL_ONE GL_ONE } }
    textures/x/water { surfaceparm water surfaceparm trans
        { map textures/x/water.tga
          blendFunc blend } }
    textures/x/mirror { portal { map textures/x/mirror.tga } }
    textures/x/sky { surfaceparm sky q3map_sun 1 0.9 0.8 150 45 60 q3map_surfacelight 80 skyparms - 512 - }
    textures/x/lamp { surfaceparm nodraw }
    """
    shaders = parse_shader_text(text, "scripts/x.shader")
    lamp = shaders["textures/x/lamp"]
    assert lamp.surfacelight == 2500 and lamp.light_image == "textures/x/lamp_glow.tga"
    assert lamp.blend_mode == "opaque" and lamp.diffuse_image == "textures/x/lamp.tga"
    assert lamp.light_image_candidates()[:2] == ["textures/x/lamp_glow.tga", "textures/x/lamp_ed.tga"]
    assert "nodraw" not in lamp.surfaceparms  # the second definition in the same text is ignored
    grate = shaders["textures/x/grate"]
    assert grate.alpha_stage.alpha_func == "ge128" and grate.cull == "none" and "trans" in grate.surfaceparms
    assert shaders["textures/x/beam"].blend_mode == "add"
    assert shaders["textures/x/water"].blend_mode == "blend"
    assert shaders["textures/x/mirror"].portal
    sky = shaders["textures/x/sky"]
    assert sky.sky and sky.suns == [((1.0, 0.9, 0.8), 150.0, 45.0, 60.0)] and sky.surfacelight == 80
    assert ShaderInfo(name="textures/y/plain").diffuse_image == "textures/y/plain"  # implicit shader
    assert Stage("a.tga", ("gl_dst_color", "gl_one")).blend_mode == "add"
    assert Stage("a.tga", ("gl_zero", "gl_src_color")).blend_mode == "filter"


def test10_face_classification():
    from suite.core.scene.q3.convert import FLAGS, _excluded_reason, _kind, _shader_flags

    shaders = parse_shader_text("""
        a/sky { surfaceparm sky }
        a/fogvol { surfaceparm fog fogparms ( 1 0 0 ) 300 }
        a/lava { surfaceparm fog surfaceparm lava surfaceparm trans q3map_surfacelight 750 { map a/lava.tga } }
        a/beam { { map a/beam.tga blendfunc add } }
        a/decal { polygonOffset { map a/decal.tga blendfunc blend } }
        a/sprite { deformVertexes autosprite { map a/f.tga blendfunc blend } }
        a/water { surfaceparm water surfaceparm trans { map a/w.tga blendfunc blend } }
        a/mirror { portal { map a/m.tga blendfunc blend } }
        a/grate { { map a/g.tga alphaFunc GT0 } }
    """)
    got = {}
    for name, info in shaders.items():
        flags = _shader_flags(info, 0, 1)
        got[name] = (_excluded_reason(flags), _kind(flags))
    assert got == {"a/sky": ("sky", "diffuse"), "a/fogvol": ("fog", "diffuse"), "a/lava": (None, "diffuse"),
                   "a/beam": ("additive", "diffuse"), "a/decal": ("decal", "glass"),
                   "a/sprite": ("sprite", "glass"), "a/water": (None, "glass"), "a/mirror": (None, "mirror"),
                   "a/grate": (None, "diffuse")}
    assert _shader_flags(shaders["a/grate"], 0, 1) & FLAGS["alpha_test"]
    # Compiled flags alone (a shader without a script) also count: SURF_NODRAW, SURF_SKY.
    assert _excluded_reason(_shader_flags(ShaderInfo(name="n"), 0x80, 1)) == "nodraw"
    assert _excluded_reason(_shader_flags(ShaderInfo(name="s"), 0x4, 1)) == "sky"
