"""The embedded default scenes, generated deterministically in code (nothing is downloaded).

``EMBEDDED`` maps a scene name to a function that builds it:

- ``cornell``: Mitsuba's own ``mi.cornell_box()`` through the Mitsuba loader, with a gentle orbit.
- ``living_room``: a closed pink room with furniture blocks and 3 point lights, after the test scene of
  seed 000 (the visibility-bitmap paper shades a pink room lit by three lights).
- ``atrium``: a colonnaded courtyard in the spirit of Sponza: two storeys of arcades, open to the sky, lit by
  emissive quads under the gallery ceilings and by point lights (for layered_pvs and RAIL).
- ``arena``: a Quake-like level of 8 rooms joined by corridors with 73 point lights, so light culling matters
  (for quake_drt). It has one moving platform and one moving light, so dynamic-scene code paths run.

Every camera path lasts about 4 s at 30 fps and contains a walk, a fast turn (90 deg of yaw in 0.3 s) and a
backward move: the cases where reprojection has to fill disocclusions. Units: metres, y up; point lights in
W/sr and area lights in radiance (Mitsuba's units). Intensities give a mean pixel radiance of roughly 0.1-0.5
at exposure 1 under direct lighting.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from suite.core.scene.builder import CameraScript, SceneBuilder
from suite.core.scene.model import CameraKey, CameraPath, Scene

DEFAULT_RESOLUTION = (320, 180)
DEFAULT_FPS = 30.0
WARM_WHITE = np.array([1.0, 0.88, 0.72])

# The fast turn in every path: 90 deg of yaw in 0.3 s (300 deg/s), a whip-pan that reprojection must survive.
FAST_TURN_DEG = 90.0
FAST_TURN_S = 0.3


def _axis_rect(b: SceneBuilder, normal_axis: int, coord: float, range_a, range_b, facing: float, material,
               obj=None):
    """An axis-aligned rectangle in the plane ``x[normal_axis] = coord`` whose front faces ``facing`` (+1/-1)
    along that axis. ``range_a``/``range_b`` span the next two axes in cyclic order (x -> y, z; y -> z, x;
    z -> x, y)."""
    a, c = (normal_axis + 1) % 3, (normal_axis + 2) % 3
    center = np.zeros(3)
    center[normal_axis] = coord
    center[a], center[c] = (range_a[0] + range_a[1]) / 2, (range_b[0] + range_b[1]) / 2
    u, v = np.zeros(3), np.zeros(3)
    u[a], v[c] = (range_a[1] - range_a[0]) / 2, (range_b[1] - range_b[0]) / 2  # cross(e_a, e_c) = +e_normal
    if facing < 0:
        u, v = v, u
    return b.add_quad((center, u, v), material, obj)


def _quad_facing(b: SceneBuilder, corners, facing, material, obj=None):
    """A planar quad given by 4 corners in either order, oriented so that its front faces ``facing``."""
    corners = np.asarray(corners, np.float64)
    normal = np.cross(corners[2] - corners[0], corners[3] - corners[1])
    if np.dot(normal, facing) < 0:
        corners = corners[::-1]
    return b.add_quad(corners, material, obj)


def _checker_texture(tiles_u: int, tiles_v: int, color_a, color_b, texels_per_tile: int = 8) -> np.ndarray:
    """A (H, W, 3) checkerboard of ``tiles_u`` x ``tiles_v`` tiles, for floors where reprojection error shows."""
    iu = np.arange(tiles_u * texels_per_tile) // texels_per_tile
    iv = np.arange(tiles_v * texels_per_tile) // texels_per_tile
    parity = (iv[:, None] + iu[None, :]) % 2
    return np.where(parity[..., None] == 0, np.asarray(color_a, np.float32), np.asarray(color_b, np.float32))


# --- living_room ----------------------------------------------------------------------------------

def living_room() -> Scene:
    """A 6 m x 5 m x 2.7 m closed pink room (x in [-3, 3], z in [-2.5, 2.5]) with 3 point lights."""
    b = SceneBuilder()
    wall = b.add_material("pink_wall", albedo=(0.78, 0.47, 0.52))
    floor = b.add_material("wood_floor", albedo=(0.45, 0.30, 0.19))
    ceiling = b.add_material("ceiling", albedo=(0.80, 0.78, 0.76))
    fabric = b.add_material("sofa_fabric", albedo=(0.20, 0.34, 0.40))
    wood = b.add_material("table_wood", albedo=(0.50, 0.33, 0.20))
    rug = b.add_material("rug", albedo=(0.72, 0.66, 0.56))
    shelf = b.add_material("shelf_white", albedo=(0.75, 0.75, 0.72))
    metal = b.add_material("lamp_metal", albedo=(0.25, 0.25, 0.25))
    screen = b.add_material("tv_screen", albedo=(0.03, 0.03, 0.035))
    books = [b.add_material(f"book_{i}", albedo=c) for i, c in
             enumerate([(0.60, 0.12, 0.10), (0.15, 0.30, 0.55), (0.70, 0.60, 0.20), (0.20, 0.45, 0.20)])]
    canvas = b.add_material("painting", albedo=(0.35, 0.55, 0.65))

    # Room shell: one inward-facing box split by material (the floor is the -y face, the ceiling the +y one).
    lo, hi = (-3.0, 0.0, -2.5), (3.0, 2.7, 2.5)
    b.add_box(lo, hi, wall, open_faces=("-y", "+y"), inward=True)
    b.add_box(lo, hi, floor, open_faces=("-x", "+x", "+y", "-z", "+z"), inward=True)
    b.add_box(lo, hi, ceiling, open_faces=("-x", "+x", "-y", "-z", "+z"), inward=True)

    # Sofa against the back wall: a full-width backrest, then seat and armrests in front of it. Faces that
    # touch a neighbour (or the floor) are left out, so no two coplanar faces overlap: coincident faces would
    # make the hit primitive depend on the tracing backend.
    b.add_box((-1.38, 0.0, -2.45), (1.38, 0.90, -2.15), fabric, open_faces=("-y",))
    b.add_box((-1.2, 0.0, -2.15), (1.2, 0.42, -1.6), fabric, open_faces=("-y", "-x", "+x", "-z"))
    b.add_box((-1.38, 0.0, -2.15), (-1.2, 0.62, -1.6), fabric, open_faces=("-y", "-z"))
    b.add_box((1.2, 0.0, -2.15), (1.38, 0.62, -1.6), fabric, open_faces=("-y", "-z"))
    b.add_box((-0.9, 1.3, -2.5 + 0.001), (0.9, 2.1, -2.46), canvas, open_faces=("-z",))  # painting on the wall
    # Rug and coffee table in front of the sofa.
    b.add_box((-1.6, 0.0, -1.75), (1.6, 0.012, 0.4), rug, open_faces=("-y",))
    b.add_box((-0.65, 0.38, -1.25), (0.65, 0.43, -0.45), wood)
    for x in (-0.6, 0.55):
        for z in (-1.2, -0.55):
            b.add_box((x, 0.012, z), (x + 0.05, 0.38, z + 0.05), wood, open_faces=("-y", "+y"))
    # Shelf against the right wall, with a few books.
    x0, x1, z0, z1 = 2.62, 2.98, -1.0, 0.6
    b.add_box((x0, 0.0, z0), (x1, 1.9, z0 + 0.03), shelf, open_faces=("-y",))
    b.add_box((x0, 0.0, z1 - 0.03), (x1, 1.9, z1), shelf, open_faces=("-y",))
    for k, y in enumerate((0.0, 0.45, 0.9, 1.35, 1.87)):
        b.add_box((x0, y, z0 + 0.03), (x1, y + 0.03, z1 - 0.03), shelf,
                  open_faces=("-z", "+z") + (("-y",) if k == 0 else ()))
        if k < 4:
            for j in range(5):
                za = z0 + 0.12 + 0.27 * j
                b.add_box((x0 + 0.05, y + 0.03, za), (x1 - 0.04, y + 0.03 + 0.22 + 0.03 * ((j + k) % 3), za + 0.1),
                          books[(j + k) % len(books)], open_faces=("-y",))
    # TV cabinet and screen on the left wall.
    b.add_box((-2.98, 0.0, -0.8), (-2.55, 0.5, 0.8), wood, open_faces=("-y",))
    b.add_box((-2.9, 0.5, -0.65), (-2.84, 1.2, 0.65), screen, open_faces=("-y",))
    # Floor lamp next to the sofa: base, pole and a small cap; the lamp's light sits just above the cap.
    b.add_cylinder((1.75, 0.0, -1.95), 0.18, 0.03, 24, metal, caps=(False, True))
    b.add_cylinder((1.75, 0.03, -1.95), 0.02, 1.45, 8, metal, caps=(False, False))
    b.add_cylinder((1.75, 1.48, -1.95), 0.12, 0.04, 24, metal)
    # Side table with a plant pot near the front-right corner.
    b.add_box((1.9, 0.0, 1.5), (2.6, 0.55, 2.2), wood, open_faces=("-y",))
    b.add_cylinder((2.25, 0.55, 1.85), 0.14, 0.25, 16, shelf, caps=(False, True))

    # Lights keep >= 0.5 m from the nearest surface: radiance under a point light grows as 1/d^2, and a light
    # close to a wall would burn a clipped hot spot that dominates every image metric.
    b.add_point_light("ceiling_light", (0.0, 2.1, -0.3), 6.0 * WARM_WHITE)
    b.add_point_light("floor_lamp", (1.75, 1.62, -1.95), 4.0 * WARM_WHITE)
    b.add_point_light("wall_sconce", (-2.4, 2.0, 1.7), 3.5 * np.array([1.0, 0.95, 0.9]))

    cam = CameraScript((0.5, 1.55, 2.0), yaw_deg=0.0, pitch_deg=-10.0)
    cam.walk(1.2, 1.2)                      # walk toward the sofa
    cam.hold(0.2)
    cam.turn(FAST_TURN_DEG, FAST_TURN_S)    # whip-pan left to the TV wall
    cam.walk(0.6, 0.6)
    cam.walk(-1.2, 1.0)                     # back away from the TV (moving against the view direction)
    cam.turn(-45.0, 0.7)                    # slow pan back toward the sofa corner
    b.set_camera(cam.keys, fov_deg=70.0, resolution=DEFAULT_RESOLUTION, fps=DEFAULT_FPS)
    return b.build("living_room",
                   "Closed pink living room (6 x 5 x 2.7 m) with a sofa, coffee table, rug, shelf with books, TV "
                   "and floor lamp, lit by exactly 3 point lights (ceiling, floor lamp, wall sconce), after the pink "
                   "test room of the visibility-bitmap paper (seed 000). Static. Camera: walk, 90 deg turn in "
                   "0.3 s, backward move, slow pan.")


# --- atrium ---------------------------------------------------------------------------------------

def _arch_wall(b: SceneBuilder, x0: float, x1: float, y_spring: float, y_top: float, z_front: float,
               z_back: float, material, segments: int = 12) -> None:
    """A wall between two column centres ``x0 < x1`` pierced by a semicircular arch springing at
    ``y_spring``. It has faces at ``z_front`` (facing -z) and ``z_back`` (facing +z) and the arch's
    underside; its top, sides and the strips it rests on are covered by neighbours, so they are left out."""
    cx, half = (x0 + x1) / 2, (x1 - x0) / 2
    radius = half - ARCADE_ABACUS_HALF_M
    corner = np.arctan2(y_top - y_spring, half)
    angles = np.unique(np.round(np.concatenate([np.linspace(0.0, np.pi, segments + 1), [corner, np.pi - corner]]), 9))

    def arc(theta):
        return np.array([cx + radius * np.cos(theta), y_spring + radius * np.sin(theta)])

    def rim(theta):
        # Where the ray from the arch centre at angle theta leaves the wall's outline rectangle.
        d = np.array([np.cos(theta), np.sin(theta)])
        t_side = half / abs(d[0]) if abs(d[0]) > 1e-12 else np.inf
        t_top = (y_top - y_spring) / d[1] if d[1] > 1e-12 else np.inf
        return np.array([cx, y_spring]) + min(t_side, t_top) * d

    quads, facings = [], []
    for t0, t1 in zip(angles[:-1], angles[1:]):
        outline = [arc(t0), arc(t1), rim(t1), rim(t0)]
        for z, facing in ((z_front, -1.0), (z_back, 1.0)):
            quads.append([(p[0], p[1], z) for p in outline])
            facings.append((0.0, 0.0, facing))
    for t0, t1 in zip(angles[:-1], angles[1:]):  # the same angles as the faces, so the edges meet exactly
        p0, p1, mid = arc(t0), arc(t1), (t0 + t1) / 2
        quads.append([(p0[0], p0[1], z_front), (p1[0], p1[1], z_front), (p1[0], p1[1], z_back),
                      (p0[0], p0[1], z_back)])
        facings.append((-np.cos(mid), -np.sin(mid), 0.0))  # the arch's underside faces its centre
    b.add_quads(quads, material, facing=facings)


ARCADE_ABACUS_HALF_M = 0.22  # half-width of the block on each column top that the arches spring from


def atrium() -> Scene:
    """A 16 m x 11 m courtyard (x in [-8, 8], z in [-5.5, 5.5]) with two-storey arcades on both long sides."""
    b = SceneBuilder()
    stone = b.add_material("stone", albedo=(0.62, 0.56, 0.46))
    column_mat = b.add_material("column_stone", albedo=(0.70, 0.66, 0.58))
    plaster = b.add_material("plaster", albedo=(0.66, 0.52, 0.40))
    gallery_floor = b.add_material("gallery_floor", albedo=(0.45, 0.40, 0.34))
    court_tiles = b.add_material("court_tiles", albedo=(0.48, 0.43, 0.36),
                                 texture=_checker_texture(6, 16, (0.56, 0.50, 0.42), (0.40, 0.36, 0.30)))
    curtain = [b.add_material(f"curtain_{i}", albedo=c)
               for i, c in enumerate([(0.55, 0.12, 0.10), (0.12, 0.35, 0.18), (0.15, 0.20, 0.50)])]

    court_half_x, court_half_z = 8.0, 3.0
    wall_z, wall_t = 5.5, 0.4
    arcade_half_depth = 0.25  # arcade walls and abaci are 0.5 m deep, centred on the column line
    ground_top, upper_spring, upper_floor = 3.2, 4.4, 4.7
    upper_top, roof_top = 7.1, 8.1
    roof_band = 8.4
    column_x = np.arange(-court_half_x, court_half_x + 1e-9, 2.0)

    # Floors: the court (tiled, exactly the open area) and the two gallery floors, all facing up.
    _axis_rect(b, 1, 0.0, (-court_half_z + arcade_half_depth, court_half_z - arcade_half_depth),
               (-court_half_x, court_half_x), 1.0, court_tiles)
    for s in (-1.0, 1.0):
        z_in, z_out = s * (court_half_z - arcade_half_depth), s * wall_z
        _axis_rect(b, 1, 0.0, tuple(sorted((z_in, z_out))), (-court_half_x, court_half_x), 1.0, gallery_floor)
    # Outer walls behind the galleries and the two end walls, full height (outer sides are never seen).
    for s in (-1.0, 1.0):
        z_lo, z_hi = sorted((s * wall_z, s * (wall_z + wall_t)))
        b.add_box((-court_half_x - wall_t, 0.0, z_lo), (court_half_x + wall_t, roof_band, z_hi), plaster,
                  open_faces=("-y",))
        x_lo, x_hi = sorted((s * court_half_x, s * (court_half_x + wall_t)))
        b.add_box((x_lo, 0.0, -wall_z), (x_hi, roof_band, wall_z), plaster, open_faces=("-y", "-z", "+z"))
    # Curtains hung in the ground-floor gallery, one per few bays (colour varies along the wall).
    for i, x in enumerate((-5.0, 1.0, 5.0)):
        for s in (-1.0, 1.0):
            z_lo, z_hi = sorted((s * (wall_z - 0.05), s * (wall_z - 0.01)))
            b.add_box((x - 0.7, 0.4, z_lo), (x + 0.7, 3.6, z_hi), curtain[i % 3],
                      open_faces=("+z",) if s > 0 else ("-z",))

    for s in (-1.0, 1.0):
        zc = s * court_half_z
        z_front, z_back = zc - arcade_half_depth, zc + arcade_half_depth
        slab_z = tuple(sorted((z_front if s > 0 else z_back, s * wall_z)))
        for y_floor, y_spring, y_top in ((0.0, ground_top, upper_spring), (upper_floor, upper_top, roof_top)):
            # Columns with an abacus block; arches spring from the abacus tops.
            for x in column_x:
                b.add_cylinder((x, y_floor, zc), 0.19, y_spring - 0.15 - y_floor, 16, column_mat, caps=(False, False))
                x_lo, x_hi = max(x - ARCADE_ABACUS_HALF_M, -court_half_x), min(x + ARCADE_ABACUS_HALF_M, court_half_x)
                against_end_wall = ("-x",) if x_lo <= -court_half_x else ("+x",) if x_hi >= court_half_x else ()
                b.add_box((x_lo, y_spring - 0.15, z_front), (x_hi, y_spring, z_back), stone,
                          open_faces=("+y",) + against_end_wall)
            for xa, xb in zip(column_x[:-1], column_x[1:]):
                _arch_wall(b, xa, xb, y_spring, y_top, z_front, z_back, stone)
        # The upper gallery's floor slab and the roof band over the upper gallery (the court stays open).
        b.add_box((-court_half_x, upper_spring, slab_z[0]), (court_half_x, upper_floor, slab_z[1]), stone,
                  open_faces=("-x", "+x", "+z" if s > 0 else "-z"))
        b.add_box((-court_half_x, roof_top, slab_z[0]), (court_half_x, roof_band, slab_z[1]), stone,
                  open_faces=("-x", "+x", "+z" if s > 0 else "-z"))
        # Area lights: emissive panels just under the ground-floor gallery ceiling, facing down.
        z_light = s * (court_half_z + wall_z) / 2
        for x in (-5.0, -1.0, 1.0, 5.0):
            b.add_area_light_quad(f"gallery_panel_{'north' if s < 0 else 'south'}_{x:+.0f}",
                                  (x, upper_spring - 0.02, z_light), (0.6, 0.6), (0.0, -1.0, 0.0),
                                  radiance=40.0 * WARM_WHITE)
        # Point lights: lanterns in the upper gallery.
        for x in (-4.0, 4.0):
            b.add_point_light(f"upper_lantern_{'north' if s < 0 else 'south'}_{x:+.0f}",
                              (x, upper_floor + 2.0, s * (court_half_z + wall_z) / 2), 2.5 * WARM_WHITE)
    # Point lights hanging over the open court.
    for x in (-5.0, 0.0, 5.0):
        b.add_point_light(f"court_lantern_{x:+.0f}", (x, 3.6, 0.0), 6.0 * WARM_WHITE)

    cam = CameraScript((6.5, 1.7, 0.0), yaw_deg=90.0, pitch_deg=5.0)  # at the east end, looking west (-x)
    cam.walk(1.5, 1.5)                      # walk down the court to the middle of a bay
    cam.turn(FAST_TURN_DEG, FAST_TURN_S)    # whip-pan left to face the south arcade (+z)
    cam.walk(1.5, 0.8)                      # approach the arcade
    cam.hold(0.1)
    cam.walk(-3.0, 1.0)                     # back away across the court
    cam.turn(-40.0, 0.6, pitch_deg=15.0)    # look up toward the upper gallery
    b.set_camera(cam.keys, fov_deg=75.0, resolution=DEFAULT_RESOLUTION, fps=DEFAULT_FPS)
    return b.build("atrium",
                   "Sponza-like courtyard (16 x 11 m, open to the sky) with two storeys of arcades (columns, "
                   "semicircular arches, gallery floor slab, roof band) on both long sides, a tiled court floor "
                   "(checker texture) and curtains; lit by 8 emissive panels under the ground-floor gallery ceilings "
                   "and 7 point lights (court and upper-gallery lanterns). Static. Camera: walk, 90 deg turn in "
                   "0.3 s, approach, backward move, upward pan.")


# --- arena ----------------------------------------------------------------------------------------

ARENA_GRID = (4, 2)  # rooms along x, along z
ARENA_ROOM_SPACING_M = 14.0
ARENA_ROOM_HALF_M = 5.0  # rooms are 10 m x 10 m; corridors between room walls are 4 m long
ARENA_ROOM_HEIGHTS_M = (4.5, 5.5, 4.5, 6.0, 5.0, 4.5, 6.0, 5.0)
ARENA_CORRIDOR_HALF_WIDTH_M = 1.2
ARENA_CORRIDOR_HEIGHT_M = 2.8
ARENA_DOOR_OFFSET_M = 2.5  # doors sit off the wall centre, so no straight line joins two room centres


def arena_corridors() -> list[tuple[tuple[int, int], tuple[int, int], float]]:
    """(room a, room b, door offset) for every corridor, rooms as (ix, iz) grid cells. Along x every
    neighbour pair is joined; along z only columns 0 and 2, so the level has loops and dead ends."""
    nx, nz = ARENA_GRID
    out = []
    for iz in range(nz):
        for ix in range(nx - 1):
            out.append(((ix, iz), (ix + 1, iz), ARENA_DOOR_OFFSET_M * (1 if (ix + iz) % 2 == 0 else -1)))
    for ix in (0, 2):
        out.append(((ix, 0), (ix, 1), ARENA_DOOR_OFFSET_M * (1 if ix % 4 == 0 else -1)))
    return out


def arena_room_centers() -> np.ndarray:
    """(R, 3) floor centres of the arena rooms, in room index order (ix + nx * iz)."""
    nx, nz = ARENA_GRID
    return np.array([(ix * ARENA_ROOM_SPACING_M, 0.0, iz * ARENA_ROOM_SPACING_M)
                     for iz in range(nz) for ix in range(nx)])


def _wall_with_doors(b: SceneBuilder, axis: int, coord: float, span, height: float, doors, facing: float,
                     material) -> None:
    """A vertical wall in the plane ``x[axis] = coord`` (axis 0 or 2) spanning ``span`` along the other
    horizontal axis, floor to ``height``, with door holes ``[(lo, hi, door_height), ...]``."""
    edges = [span[0]]
    for lo, hi, _ in sorted(doors):
        edges += [lo, hi]
    edges.append(span[1])
    pieces = [(edges[i], edges[i + 1], 0.0) for i in range(0, len(edges), 2)]
    pieces += [(lo, hi, dh) for lo, hi, dh in doors]  # the lintel above each door
    for lo, hi, y0 in pieces:
        if hi - lo < 1e-9:
            continue
        if axis == 0:  # plane x = coord: cyclic axes are (y, z)
            _axis_rect(b, 0, coord, (y0, height), (lo, hi), facing, material)
        else:  # plane z = coord: cyclic axes are (x, y)
            _axis_rect(b, 2, coord, (lo, hi), (y0, height), facing, material)


def arena() -> Scene:
    """8 rooms on a 4 x 2 grid, joined by 8 corridors, lit by 73 point lights; rooms face inward."""
    b = SceneBuilder()
    floor = b.add_material("floor_metal", albedo=(0.42, 0.40, 0.38))
    ceiling = b.add_material("ceiling_dark", albedo=(0.30, 0.29, 0.28))
    corridor = b.add_material("corridor_wall", albedo=(0.50, 0.45, 0.38))
    wall_colours = [(0.60, 0.42, 0.32), (0.42, 0.50, 0.58), (0.55, 0.55, 0.45), (0.58, 0.38, 0.38),
                    (0.40, 0.55, 0.42), (0.55, 0.48, 0.60), (0.62, 0.52, 0.35), (0.45, 0.45, 0.50)]
    walls = [b.add_material(f"room_wall_{i}", albedo=c) for i, c in enumerate(wall_colours)]
    crate = b.add_material("crate", albedo=(0.55, 0.40, 0.22))
    pillar = b.add_material("pillar", albedo=(0.55, 0.55, 0.55))
    platform_mat = b.add_material("platform", albedo=(0.65, 0.30, 0.12))

    nx, nz = ARENA_GRID
    centers = arena_room_centers()
    corridors = arena_corridors()
    h = ARENA_ROOM_HALF_M
    cw, ch = ARENA_CORRIDOR_HALF_WIDTH_M, ARENA_CORRIDOR_HEIGHT_M

    # Door holes per (room, wall): wall key (axis, side) with side +1 = the wall at +h along that axis.
    doors: dict[tuple[int, int, int], list] = {}
    for (a, c, offset) in corridors:
        ia, ic = a[0] + nx * a[1], c[0] + nx * c[1]
        axis = 0 if a[1] == c[1] else 2
        other = 2 - axis  # the horizontal axis along the wall
        centre_along = centers[ia][other] + offset
        hole = (centre_along - cw, centre_along + cw, ch)
        doors.setdefault((ia, axis, 1), []).append(hole)
        doors.setdefault((ic, axis, -1), []).append(hole)

    for r, c in enumerate(centers):
        height = ARENA_ROOM_HEIGHTS_M[r]
        _axis_rect(b, 1, 0.0, (c[2] - h, c[2] + h), (c[0] - h, c[0] + h), 1.0, floor)
        _axis_rect(b, 1, height, (c[2] - h, c[2] + h), (c[0] - h, c[0] + h), -1.0, ceiling)
        for axis in (0, 2):
            other = 2 - axis
            for side in (-1, 1):
                _wall_with_doors(b, axis, c[axis] + side * h, (c[other] - h, c[other] + h), height,
                                 doors.get((r, axis, side), []), -float(side), walls[r])

    for (a, cc, offset) in corridors:
        ia, ic = a[0] + nx * a[1], cc[0] + nx * cc[1]
        axis = 0 if a[1] == cc[1] else 2
        other = 2 - axis
        start, end = centers[ia][axis] + h, centers[ic][axis] - h
        along = centers[ia][other] + offset
        if axis == 0:  # corridor along x; floor/ceiling rect axes are (z, x)
            _axis_rect(b, 1, 0.0, (along - cw, along + cw), (start, end), 1.0, floor)
            _axis_rect(b, 1, ch, (along - cw, along + cw), (start, end), -1.0, ceiling)
            _axis_rect(b, 2, along - cw, (start, end), (0.0, ch), 1.0, corridor)
            _axis_rect(b, 2, along + cw, (start, end), (0.0, ch), -1.0, corridor)
        else:  # corridor along z
            _axis_rect(b, 1, 0.0, (start, end), (along - cw, along + cw), 1.0, floor)
            _axis_rect(b, 1, ch, (start, end), (along - cw, along + cw), -1.0, ceiling)
            _axis_rect(b, 0, along - cw, (0.0, ch), (start, end), 1.0, corridor)
            _axis_rect(b, 0, along + cw, (0.0, ch), (start, end), -1.0, corridor)
        mid = (start + end) / 2
        pos = (mid, ch - 0.35, along) if axis == 0 else (along, ch - 0.35, mid)
        b.add_point_light(f"corridor_{ia}_{ic}", pos, 4.0 * WARM_WHITE)

    # Props: pillars in the odd rooms, crate stacks in the even ones (deterministic by room index).
    for r, c in enumerate(centers):
        if r % 2 == 1:
            for dx, dz in ((-2.0, -2.0), (2.0, 2.0)):
                b.add_cylinder((c[0] + dx, 0.0, c[2] + dz), 0.35, ARENA_ROOM_HEIGHTS_M[r], 16, pillar,
                               caps=(False, False))
        else:
            # Two crates 4 cm apart with a third resting on both (its bottom is left out).
            for k, (dx, dz, size) in enumerate(((2.5, -2.8, 0.96), (3.5, -2.8, 0.96), (3.0, -2.8, 0.8))):
                y0 = 0.96 if k == 2 else 0.0
                b.add_box((c[0] + dx - size / 2, y0, c[2] + dz - size / 2),
                          (c[0] + dx + size / 2, y0 + size, c[2] + dz + size / 2), crate,
                          open_faces=("-y",))

    # Eight lights per room: four high in the corners, four lower around the middle; colour varies by room.
    tints = [(1.0, 0.85, 0.7), (0.75, 0.85, 1.0), (1.0, 0.95, 0.85), (1.0, 0.75, 0.7),
             (0.8, 1.0, 0.8), (0.9, 0.8, 1.0), (1.0, 0.9, 0.6), (0.85, 0.9, 1.0)]
    for r, c in enumerate(centers):
        height = ARENA_ROOM_HEIGHTS_M[r]
        spots = [(sx * 3.5, height - 0.6, sz * 3.5) for sx in (-1, 1) for sz in (-1, 1)]
        spots += [(sx * 1.2, 1.8, sz * 1.2) for sx, sz in ((-1, 0), (1, 0), (0, -1), (0, 1))]
        for k, (dx, y, dz) in enumerate(spots):
            b.add_point_light(f"room{r}_light{k}", (c[0] + dx, y, c[2] + dz),
                              (6.0 if k < 4 else 3.0) * np.array(tints[r]))

    # Dynamic parts, both in room 0 where the camera path starts.
    # DYNAMIC OBJECT: a floating platform sliding back and forth along x (4 s period).
    platform = b.new_object("moving_platform")
    b.add_box((-3.5, 0.9, -3.5), (-1.5, 1.2, -1.5), platform_mat, platform)
    b.add_object_animation(platform, [0.0, 2.0, 4.0], [(0.0, 0.0, 0.0), (3.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
    # DYNAMIC LIGHT: a light gliding across room 0 above the platform's track.
    moving = b.add_point_light("moving_light", (-3.0, 2.6, -1.0), 5.0 * np.array([0.7, 0.9, 1.0]))
    b.add_light_animation(moving, [0.0, 2.0, 4.0], [(-3.0, 2.6, -1.0), (3.0, 2.6, 1.0), (-3.0, 2.6, -1.0)])

    cam = CameraScript((-3.5, 1.7, 2.5), yaw_deg=-90.0, pitch_deg=-5.0)  # in room 0, looking +x down the door line
    cam.walk(5.5, 1.6)                      # run toward the door to room 1
    cam.turn(FAST_TURN_DEG, FAST_TURN_S)    # whip-pan left (toward -z) onto the platform and the crates
    cam.hold(0.2)
    cam.walk(-1.8, 0.9)                     # back-pedal toward the +z wall
    cam.turn(-90.0, 1.0)                    # turn back toward the corridor to room 1
    b.set_camera(cam.keys, fov_deg=80.0, resolution=DEFAULT_RESOLUTION, fps=DEFAULT_FPS)
    return b.build("arena",
                   "Quake-like level: 8 rooms (10 x 10 m, 4.5-6 m high) on a 4 x 2 grid joined by 8 corridors "
                   "with off-centre doors, so walls occlude between rooms; pillars and crates; 73 point lights "
                   "(8 per room, 1 per corridor, 1 moving) so light culling matters. Dynamic: object "
                   "'moving_platform' slides along x in room 0 and light 'moving_light' glides across room 0. "
                   "Camera: run, 90 deg turn in 0.3 s, back-pedal, turn.")


# --- cornell --------------------------------------------------------------------------------------

def cornell_camera_path() -> CameraPath:
    """A gentle path around ``mi.cornell_box()``'s sensor (at (0, 0, 3.9) looking at the origin): an orbit
    of +-8 deg, then a dolly in by 0.5 m and back out (a backward move)."""
    radius, target = 3.9, np.zeros(3)

    def orbit(t_s, yaw_deg, dist):
        a = np.radians(yaw_deg)
        return CameraKey(t_s, np.array([dist * np.sin(a), 0.0, dist * np.cos(a)]), target)

    keys = [orbit(0.0, 0.0, radius), orbit(1.0, 8.0, radius), orbit(2.0, -8.0, radius),
            orbit(2.5, 0.0, radius), orbit(3.25, 0.0, radius - 0.5), orbit(4.0, 0.0, radius)]
    return CameraPath(keys=keys, fov_deg=39.3077, resolution=(256, 256), fps=DEFAULT_FPS)


def _cornell() -> Scene:
    """Mitsuba's cornell_box(): a closed box with one area light, two blocks; a gentle orbit and dolly."""
    from suite.core.env import mitsuba
    from suite.core.scene.mitsuba_io import load_mitsuba

    mi = mitsuba(None)  # reading only: the default variant (suite.core.env.default_variant)
    return load_mitsuba(mi.cornell_box(), name="cornell", camera_path=cornell_camera_path())


# --- gallery --------------------------------------------------------------------------------------

def _grate_opacity(size: int = 64) -> np.ndarray:
    """(size, size) binary opacity of a grate: a frame, four vertical bars and a cross bar (1 = solid)."""
    u = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(u, u, indexing="xy")
    frame = (uu < 0.08) | (uu > 0.92) | (vv < 0.08) | (vv > 0.92)
    bars = (np.abs((uu * 5.0) % 1.0 - 0.5) < 0.12) | (np.abs(vv - 0.55) < 0.05)
    return (frame | bars).astype(np.float32)


def gallery() -> Scene:
    """A materials gallery: mirror, glass sphere, glossy metal and plastic, an alpha-tested grate, point and area light."""
    b = SceneBuilder()
    tiles = b.add_material("floor_tiles", albedo=(0.5, 0.5, 0.5),
                           texture=_checker_texture(8, 8, (0.75, 0.72, 0.66), (0.22, 0.24, 0.30)))
    back = b.add_material("back_wall", albedo=(0.55, 0.62, 0.70))
    side = b.add_material("side_wall", albedo=(0.72, 0.62, 0.48))
    white = b.add_material("pedestal", albedo=(0.80, 0.80, 0.78))
    wood = b.add_material("mirror_back", albedo=(0.30, 0.20, 0.12))
    # Parameters as in Mitsuba's plugins (suite.core.scene.model.Material).
    mirror = b.add_material("mirror", albedo=0.0, kind="mirror", specular_reflectance=(0.92, 0.92, 0.90))
    glass = b.add_material("glass", albedo=0.0, kind="glass", int_ior=1.5, ext_ior=1.0)
    gold = b.add_material("gold", albedo=0.0, kind="rough_conductor", roughness=0.2, distribution="ggx",
                          conductor_eta=(0.143, 0.375, 1.442), conductor_k=(3.983, 2.386, 1.603))
    plastic = b.add_material("red_plastic", albedo=(0.55, 0.08, 0.06), kind="rough_plastic", roughness=0.15,
                             distribution="beckmann", int_ior=1.49)
    grate = b.add_material("grate", albedo=(0.35, 0.37, 0.40), opacity_texture=_grate_opacity())

    # Room: floor, back and side walls; open above and toward the camera.
    b.add_quad(((0.0, 0.0, 0.0), (0.0, 0.0, 4.0), (4.0, 0.0, 0.0)), tiles)  # normal +y
    _axis_rect(b, 2, -4.0, (-4.0, 4.0), (0.0, 3.0), +1.0, back)
    _axis_rect(b, 0, -4.0, (0.0, 3.0), (-4.0, 4.0), +1.0, side)
    _axis_rect(b, 0, 4.0, (0.0, 3.0), (-4.0, 4.0), -1.0, side)
    # A one-sided mirror panel turned toward the room, with a wooden back 2 cm behind it.
    n = np.array([-0.8, 0.0, 0.6])
    t = np.cross([0.0, 1.0, 0.0], n)  # horizontal, cross(t, up) = n
    c = np.array([2.9, 1.3, -2.3])
    b.add_quad((c, 0.8 * t, np.array([0.0, 1.0, 0.0])), mirror)
    b.add_quad((c - 0.02 * n, np.array([0.0, 1.0, 0.0]), 0.8 * t), wood)
    # Glass sphere on a pedestal, glossy gold sphere and a plastic block on the floor.
    b.add_box((-1.35, 0.0, -1.65), (-0.65, 0.35, -0.95), white, open_faces=("-y",))
    b.add_sphere((-1.0, 0.85, -1.3), 0.5, 48, glass)
    b.add_sphere((0.7, 0.45, -2.5), 0.45, 48, gold)
    b.add_box((-3.0, 0.0, -3.2), (-2.1, 0.8, -2.3), plastic, open_faces=("-y",))
    # An alpha-tested grate standing between the key light and the floor in front of it.
    b.add_quad(((1.7, 0.7, -0.6), (0.7, 0.0, 0.0), (0.0, 0.7, 0.0)), grate)

    b.add_point_light("key", (1.6, 2.6, -1.6), 9.0 * WARM_WHITE)
    b.add_point_light("fill", (-2.6, 2.3, 0.8), 4.0 * np.array([0.85, 0.9, 1.0]))
    b.add_area_light_quad("panel", (-0.3, 2.9, -1.6), (0.8, 0.8), (0.0, -1.0, 0.0), 6.0 * WARM_WHITE)

    cam = CameraScript((0.0, 1.5, 3.2), yaw_deg=0.0, pitch_deg=-12.0)
    cam.walk(1.2, 1.2)                      # toward the objects
    cam.hold(0.2)
    cam.turn(-FAST_TURN_DEG, FAST_TURN_S)   # whip-pan right, past the mirror
    cam.walk(0.4, 0.5)
    cam.walk(-1.0, 0.9)                     # backward move
    cam.turn(60.0, 0.8)                     # pan back toward the glass sphere
    b.set_camera(cam.keys, fov_deg=70.0, resolution=DEFAULT_RESOLUTION, fps=DEFAULT_FPS)
    return b.build("gallery",
                   "Open-topped room (8 x 8 m floor) with one of each material kind: a one-sided mirror panel, a "
                   "glass sphere (IOR 1.5) on a pedestal, a gold GGX sphere (alpha 0.2), a red rough-plastic block "
                   "(Beckmann, alpha 0.15), an alpha-tested grate (binary opacity, threshold 0.5) casting a "
                   "patterned shadow; 2 point lights and one emissive panel. Static. Camera: walk, 90 deg turn in "
                   "0.3 s, backward move, pan.")


EMBEDDED: dict[str, Callable[[], Scene]] = {
    "cornell": _cornell,
    "living_room": living_room,
    "atrium": atrium,
    "arena": arena,
    "gallery": gallery,
}
