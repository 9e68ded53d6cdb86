"""Quake III lights in the suite's (Mitsuba's) units.

q3map2 (GtkRadiant ``tools/quake3/q3map2/light.c``, ``light_bounce.c``) lights a lightmap luxel with

* a point light: ``add = photons * cos / d^2`` with ``photons = intensity * pointScale`` (``pointScale`` =
  7500, ``d`` in Quake units; ``LightContributionToSample``), and ``add = photons * linearScale - d * fade``
  (``linearScale`` = 1/8000, no cosine) for a light with ``spawnflags & 1`` (linear falloff);
* a surface light (``q3map_surfacelight V``): ``add = F * V * formFactorValueScale * areaScale`` with the
  point-to-polygon form factor ``F`` (``formFactorValueScale`` = 3, ``areaScale`` = 0.25;
  ``RadSubdivideDiffuseLight``).

The engine shows a luxel value ``add`` as a multiplier ``add / 63.75`` of the texture (lightmaps are shifted by
``mapOverBrightBits`` = 2 when loaded, ``R_ColorShiftLightingBytes``: 255 / 4 = 63.75 is "texture unchanged").
A Lambertian surface of albedo rho under irradiance E has radiance rho * E / pi, so the calibration used here is
**one luxel unit = pi / 63.75 W/m^2 of irradiance**. It follows:

* point light: ``I = intensity * scale * 7500 * (pi / 63.75) * unit_m^2`` W/sr (0.2385 W/sr per unit of
  ``light`` at 1 unit = 0.0254 m; the default ``light`` 300 gives 71.5 W/sr);
* surface light: ``L_e = V * 3 * 0.25 / 63.75`` W/m^2/sr (0.01176 per unit of ``q3map_surfacelight``;
  independent of the length unit because ``F`` is dimensionless), emitted from the front of the surface;
* linear-falloff light: reaches zero at ``d0 = 0.9375 * intensity / fade`` units; it becomes the
  inverse-square light that matches it at ``d0 / 2`` (``photons_eq = (0.9375 * intensity / 2) * (d0 / 2)^2``);
* spot light (a ``target``): q3map2 lights a cone of half-angle ``atan((radius + 16) / distance to target)``
  (radius default 64) with the point light's inverse-square law. The scene model has point lights only, so a
  spot becomes a point light with its on-axis intensity (what the lit cone receives); its cone is kept in the
  light records (``Q3Info.lights``).

All of them are multiplied by ``light_scale`` (default 1). Colours (``_color``, ``q3map_lightRGB``, the average
of the light image) are normalised so that the largest component is 1 (q3map2's ColorNormalize) and, being
chosen on screen, read as sRGB-encoded and decoded to linear RGB (a normalised colour keeps its maximum of 1).
* sun (``q3map_sun r g b intensity degrees elevation`` in a sky shader the map uses): q3map2 adds
  ``intensity * cos`` to a luxel it lights (``CreateSunLight``, ``skyScale`` = 1), an irradiance of
  ``intensity * pi / 63.75`` W/m^2 at normal incidence. The scene model has no directional light, so a sun
  becomes a point light ``SUN_DISTANCE_M`` (10 km) from the centre of the map towards the sun, with
  ``I = E * SUN_DISTANCE_M^2``; over a 100 m map its direction varies by 0.3 deg and its irradiance by 1 %.
  It reaches the level through the holes the (excluded) sky faces leave.

* sky light (``q3map_surfacelight V`` on a sky shader): q3map2 makes the sky faces area lights of the
  surface-light radiance ``L`` above. Sky faces are not geometry here, so the sky becomes a dome of
  ``SKY_DOME_BANDS x SKY_DOME_AZIMUTHS`` (3 x 8) point lights ``SUN_DISTANCE_M`` away, one per equal solid
  angle cell ``dOmega = 2 pi / 24`` of the upper hemisphere (cell centres at the middle of their cos(theta)
  band), each of irradiance ``L * dOmega`` at normal incidence. Under open sky a horizontal surface then
  receives ``sum(L dOmega cos theta) = pi L``, what a uniform sky of radiance L gives; under partial sky the
  shadow rays leave through the holes the sky faces leave, like light through the sky faces.

Not reproduced: the 16-unit distance clamp, q3map2's surface-light back-splash point lights, ``_sun`` spot
suns, negative and ``lightJunior`` lights; they are counted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from suite.core.scene.q3.shaders import color_normalize
from suite.core.scene.q3.textures import srgb_to_linear

POINT_SCALE = 7500.0  # q3map2 pointScale
LINEAR_SCALE = 1.0 / 8000.0  # q3map2 linearScale
AREA_SCALE = 0.25  # q3map2 areaScale
FORM_FACTOR_VALUE_SCALE = 3.0  # q3map2 formFactorValueScale
DEFAULT_INTENSITY = 300.0  # q3map2 default for a light without light/_light
LIGHTMAP_UNITY = 255.0 / 4.0  # luxel value that leaves the texture unchanged (mapOverBrightBits = 2)
IRRADIANCE_PER_LUXEL = math.pi / LIGHTMAP_UNITY  # W/m^2 per luxel unit
SPOT_DEFAULT_RADIUS = 64.0  # q3map2: radius key default, and default distance to a target at the origin
SPOT_RADIUS_PAD = 16.0  # q3map2: radiusByDist = (radius + 16) / dist
SUN_DISTANCE_M = 1.0e4  # a sun becomes a point light this far from the map's centre
SKY_DOME_BANDS = 3  # equal-solid-angle elevation bands of the sky dome
SKY_DOME_AZIMUTHS = 8  # cells per band


def point_intensity_w_sr(photons: float, unit_m: float, light_scale: float = 1.0) -> float:
    """W/sr of a q3map2 inverse-square light with ``photons`` (= intensity * pointScale)."""
    return photons * IRRADIANCE_PER_LUXEL * unit_m ** 2 * light_scale


def surface_radiance(value: float, light_scale: float = 1.0) -> float:
    """W/m^2/sr of a q3map_surfacelight ``value``."""
    return value * FORM_FACTOR_VALUE_SCALE * AREA_SCALE / LIGHTMAP_UNITY * light_scale


def linear_equivalent_photons(intensity: float, fade: float = 1.0) -> float:
    """Photons of the inverse-square light matching a linear-falloff light at half its reach."""
    peak = intensity * POINT_SCALE * LINEAR_SCALE  # luxel value at distance 0
    half_reach = 0.5 * peak / max(fade, 1e-9)
    return 0.5 * peak * half_reach ** 2


def display_color_to_linear(rgb) -> np.ndarray:
    """A Quake colour (any scale) -> normalised (max 1) -> decoded from sRGB to linear."""
    return srgb_to_linear(color_normalize(rgb)).astype(np.float64)


def _vec(text: str | None, default=(0.0, 0.0, 0.0)) -> np.ndarray:
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        v = []
    return np.array(v[:3] if len(v) >= 3 else default, np.float64)


def _float(text: str | None) -> float:
    try:
        return float(text) if text not in (None, "") else 0.0
    except ValueError:
        return 0.0


@dataclass
class Q3Light:
    """One light entity after conversion (positions in Quake units; the scene gets scene coordinates)."""

    index: int  # entity index
    kind: str  # 'point', 'spot' or 'linear'
    origin_q3: np.ndarray
    intensity_key: float  # light / _light (times scale), Quake's number
    color: np.ndarray  # linear RGB, max 1
    intensity_w_sr: float  # scalar W/sr before colour
    spot_direction_q3: np.ndarray | None = None
    spot_half_angle_deg: float | None = None
    extra: dict = field(default_factory=dict)

    @property
    def rgb_w_sr(self) -> np.ndarray:
        return self.intensity_w_sr * self.color

    def record(self, to_scene) -> dict:
        out = {"entity": self.index, "kind": self.kind, "origin_q3": self.origin_q3.tolist(),
               "position": to_scene(self.origin_q3).tolist(), "light": self.intensity_key,
               "color": self.color.tolist(), "intensity_w_sr": self.intensity_w_sr}
        if self.spot_direction_q3 is not None:
            d = self.spot_direction_q3 @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]).T
            out.update(spot_direction=d.tolist(), spot_half_angle_deg=self.spot_half_angle_deg)
        out.update(self.extra)
        return out


def convert_light_entities(entities: list[dict[str, str]], unit_m: float, light_scale: float = 1.0):
    """(lights, skipped) from the entity list, following q3map2's CreateEntityLights.

    ``skipped`` counts light entities that cannot be represented, by reason.
    """
    targets = {}
    for e in entities:
        if "targetname" in e and e["targetname"] not in targets:
            targets[e["targetname"]] = e
    lights: list[Q3Light] = []
    skipped: dict[str, int] = {}

    def skip(reason):
        skipped[reason] = skipped.get(reason, 0) + 1

    for index, e in enumerate(entities):
        classname = e.get("classname", "")
        if classname[:11].lower() == "lightjunior":
            skip("lightJunior (light grid only)")
            continue
        if classname[:5].lower() != "light":
            continue
        if e.get("noradiosity", "")[:1] == "1":
            skip("noradiosity")
            continue
        intensity = _float(e.get("_light")) or _float(e.get("light")) or DEFAULT_INTENSITY
        intensity *= _float(e.get("scale")) or 1.0
        if intensity < 0:
            skip("negative light")
            continue
        spawnflags = int(_float(e.get("spawnflags")))
        color_text = e.get("_color")
        color = display_color_to_linear(_vec(color_text, (1.0, 1.0, 1.0))) if color_text else np.ones(3)
        origin = _vec(e.get("origin"))
        photons = intensity * POINT_SCALE
        kind = "point"
        direction = half_angle = None
        extra: dict = {}
        target = e.get("target")
        if target and target in targets:
            if e.get("_sun", "")[:1] == "1":
                skip("_sun spot (directional sun)")
                continue
            kind = "spot"
            delta = _vec(targets[target].get("origin")) - origin
            dist = float(np.linalg.norm(delta))
            direction = delta / dist if dist > 0 else np.array([0.0, 0.0, -1.0])
            radius = _float(e.get("radius")) or SPOT_DEFAULT_RADIUS
            dist = dist or SPOT_DEFAULT_RADIUS
            half_angle = math.degrees(math.atan((radius + SPOT_RADIUS_PAD) / dist))
        elif spawnflags & 1:
            kind = "linear"
            fade = _float(e.get("fade")) or 1.0
            photons = linear_equivalent_photons(intensity, fade)
            extra = {"linear_reach_units": intensity * POINT_SCALE * LINEAR_SCALE / fade}
        lights.append(Q3Light(index, kind, origin, intensity, color,
                              point_intensity_w_sr(photons, unit_m, light_scale), direction, half_angle, extra))
    return lights, skipped


def sun_light(color, intensity: float, degrees: float, elevation: float, centre_scene: np.ndarray,
              light_scale: float = 1.0):
    """(position, direction to the sun, RGB W/sr) of the point light standing in for a q3map_sun, in scene
    coordinates (the direction is Quake's ``(cos a cos e, sin a cos e, sin e)`` turned to y up)."""
    a, e = math.radians(degrees), math.radians(elevation)
    d_q3 = np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
    d = np.array([d_q3[0], d_q3[2], -d_q3[1]])
    irradiance = intensity * IRRADIANCE_PER_LUXEL * light_scale
    rgb = display_color_to_linear(color) * irradiance * SUN_DISTANCE_M ** 2
    return np.asarray(centre_scene, np.float64) + SUN_DISTANCE_M * d, d, rgb


def sky_dome_lights(radiance_rgb, centre_scene: np.ndarray):
    """(positions (N, 3), directions (N, 3), RGB W/sr (N, 3)) of the point lights standing in for a sky of
    radiance ``radiance_rgb`` (see the module docstring), in scene coordinates (y up)."""
    n_cells = SKY_DOME_BANDS * SKY_DOME_AZIMUTHS
    d_omega = 2.0 * math.pi / n_cells
    cos_t = 1.0 - (np.arange(SKY_DOME_BANDS) + 0.5) / SKY_DOME_BANDS  # band middles in cos(theta)
    phi = 2.0 * math.pi * (np.arange(SKY_DOME_AZIMUTHS) + 0.5) / SKY_DOME_AZIMUTHS
    ct, ph = np.meshgrid(cos_t, phi, indexing="ij")
    st = np.sqrt(1.0 - ct ** 2)
    dirs = np.stack([st * np.cos(ph), ct, st * np.sin(ph)], axis=-1).reshape(-1, 3)
    rgb = np.tile(np.asarray(radiance_rgb, np.float64) * d_omega * SUN_DISTANCE_M ** 2, (n_cells, 1))
    return np.asarray(centre_scene, np.float64) + SUN_DISTANCE_M * dirs, dirs, rgb
