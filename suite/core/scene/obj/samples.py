"""Small OBJ scenes written on demand, for tests and benchmarks (nothing is downloaded or stored).

* :func:`write_textured_room`: a 6 m x 3 m x 6 m room as OBJ + MTL + sidecar with a PNG checker floor, a JPEG
  brick wall, an alpha-masked grate (``map_d``, RGBA PNG), an emissive ceiling panel (``Ke``), a quad written as
  one polygon, and one material with a missing texture and statements the suite does not model (so the reports
  have something to count). The texture layout is chosen so that orientation mistakes show: the floor texture's
  top half is warm, its bottom half cool.
* :func:`write_grid_obj`: a height-field grid of ``n_triangles`` triangles with normals and texture coordinates,
  for load-time benchmarks (1 M triangles: a 74 MB file).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

FLOOR_WARM = (200, 120, 60)  # sRGB8 of the floor texture's top half (OBJ v near 1)
FLOOR_COOL = (60, 110, 190)  # bottom half (OBJ v near 0)


def write_image(path: Path, pixels: np.ndarray) -> None:
    """8-bit image (H, W, C), row 0 at the top, in the format of the file's extension (OpenImageIO)."""
    import OpenImageIO as oiio

    pixels = np.ascontiguousarray(pixels, np.uint8)
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8)):
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.write_image(pixels)
    out.close()
    if not ok:
        raise OSError(f"cannot write {path}: {out.geterror()}")


def floor_texture(size: int = 64) -> np.ndarray:
    img = np.zeros((size, size, 3), np.uint8)
    img[: size // 2] = FLOOR_WARM
    img[size // 2:] = FLOOR_COOL
    ij = np.add.outer(np.arange(size) // 8, np.arange(size) // 8) % 2 == 1
    img[ij] = (img[ij] * 0.8).astype(np.uint8)  # a checker on top, so the image has structure
    return img


def brick_texture(size: int = 64) -> np.ndarray:
    y, x = np.mgrid[:size, :size]
    mortar = (y % 16 < 2) | (((x + 16 * ((y // 16) % 2)) % 32) < 2)
    img = np.where(mortar[..., None], np.uint8([200, 195, 185]), np.uint8([150, 60, 40]))
    return img.astype(np.uint8)


def grate_alpha(size: int = 64) -> np.ndarray:
    """RGBA: opaque vertical bars 4 texels wide every 16 texels (and a frame), transparent elsewhere."""
    img = np.zeros((size, size, 4), np.uint8)
    img[..., :3] = (210, 180, 60)
    y, x = np.mgrid[:size, :size]
    bars = (x % 16 < 4) | (y < 4) | (y >= size - 4)
    img[..., 3] = np.where(bars, 255, 0)
    return img


def write_textured_room(folder: Path, name: str = "textured_room", sidecar: bool = True) -> Path:
    """Writes ``<name>.obj``, ``<name>.mtl``, the textures and ``<name>.splitbench.toml``; returns the OBJ path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "tex").mkdir(exist_ok=True)
    write_image(folder / "tex" / "floor.png", floor_texture())
    write_image(folder / "tex" / "bricks.jpg", brick_texture())
    write_image(folder / "tex" / "grate.png", grate_alpha())
    mtl = f"""# materials of {name}
newmtl floor
Kd 0.8 0.8 0.8
map_Kd tex/floor.png

newmtl bricks
Kd 0.6 0.3 0.2
map_Kd tex\\bricks.jpg

newmtl plain
Kd 0.60 0.60 0.55
Ka 0 0 0
Ks 0 0 0
illum 1

newmtl grate
Kd 0.8 0.7 0.2
map_d tex/grate.png

newmtl lamp
Kd 0 0 0
Ke 8 8 7

newmtl odd
Kd 0.3 0.5 0.3
Ks 0.5 0.5 0.5
Ns 40
map_Kd tex/nothere.png
map_bump tex/bump.png
"""
    (folder / f"{name}.mtl").write_text(mtl)
    lines = [f"# {name}: a textured test room", f"mtllib {name}.mtl"]
    nv = [0, 0, 0]  # counts of v, vt, vn written so far

    def quad(obj, material, corners, normal, uv_scale=1.0, polygon=False):
        lines.append(f"o {obj}")
        lines.append(f"usemtl {material}")
        for c in corners:
            lines.append("v {:.6f} {:.6f} {:.6f}".format(*c))
        for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
            lines.append(f"vt {u * uv_scale:.6f} {v * uv_scale:.6f}")
        lines.append("vn {:.6f} {:.6f} {:.6f}".format(*normal))
        v0, t0, n0 = nv[0] + 1, nv[1] + 1, nv[2] + 1
        ref = [f"{v0 + i}/{t0 + i}/{n0}" for i in range(4)]
        if polygon:
            lines.append("f " + " ".join(ref))
        else:
            lines.append(f"f {ref[0]} {ref[1]} {ref[2]}")
            lines.append(f"f {ref[0]} {ref[2]} {ref[3]}")
        nv[0] += 4
        nv[1] += 4
        nv[2] += 1

    # Corners counter-clockwise around the normal, starting at the texture's (0, 0) corner.
    quad("floor", "floor", [(-3, 0, 3), (3, 0, 3), (3, 0, -3), (-3, 0, -3)], (0, 1, 0), uv_scale=1.0)
    quad("back_wall", "bricks", [(-3, 0, -3), (3, 0, -3), (3, 3, -3), (-3, 3, -3)], (0, 0, 1), uv_scale=2.0)
    quad("left_wall", "plain", [(-3, 0, 3), (-3, 0, -3), (-3, 3, -3), (-3, 3, 3)], (1, 0, 0), polygon=True)
    quad("right_wall", "plain", [(3, 0, -3), (3, 0, 3), (3, 3, 3), (3, 3, -3)], (-1, 0, 0), polygon=True)
    quad("ceiling", "plain", [(-3, 3, -3), (3, 3, -3), (3, 3, 3), (-3, 3, 3)], (0, -1, 0))
    quad("front_wall", "odd", [(3, 0, 3), (-3, 0, 3), (-3, 3, 3), (3, 3, 3)], (0, 0, -1))
    quad("grate", "grate", [(-1, 0.3, -1), (1, 0.3, -1), (1, 2.3, -1), (-1, 2.3, -1)], (0, 0, 1))
    quad("lamp", "lamp", [(-0.5, 2.98, -0.5), (0.5, 2.98, -0.5), (0.5, 2.98, 0.5), (-0.5, 2.98, 0.5)], (0, -1, 0))
    (folder / f"{name}.obj").write_text("\n".join(lines) + "\n")
    if sidecar:
        (folder / f"{name}.splitbench.toml").write_text(f"""[scene]
name = "{name}"
title = "textured test room"
unit_m = 1.0
up = "y"

[[lights]]
name = "corner_lamp"
position = [1.5, 2.5, 1.0]
intensity = [3.0, 3.0, 2.8]

[camera]
position = [0.0, 1.6, 2.6]
yaw_deg = 0.0
pitch_deg = -5.0
fov_deg = 70.0
resolution = [160, 90]
moves = [{{ walk = 1.0, s = 1.0 }}, {{ turn = 90.0, s = 0.3 }}, {{ walk = -0.5, s = 0.7 }}]
""")
    return folder / f"{name}.obj"


def write_grid_obj(path: Path, n_triangles: int, seed: int = 0) -> Path:
    """A wavy height field of exactly ``n_triangles`` triangles with per-vertex texture coordinates and one
    normal, written with numpy (about 3 s per million triangles)."""
    side = int(np.ceil(np.sqrt(n_triangles / 2)))
    nx, nz = side, int(np.ceil(n_triangles / 2 / side))
    xs, zs = np.meshgrid(np.linspace(0, 100, nx + 1), np.linspace(0, 100, nz + 1))
    ys = 0.5 * np.sin(xs * 0.3 + seed) * np.cos(zs * 0.2)
    v = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    idx = np.arange((nx + 1) * (nz + 1)).reshape(nz + 1, nx + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])[:n_triangles] + 1
    with open(path, "w") as fh:
        fh.write("o grid\n")
        np.savetxt(fh, v, fmt="v %.6f %.6f %.6f")
        fh.write("vn 0 1 0\n")
        np.savetxt(fh, v[:, [0, 2]] / 100.0, fmt="vt %.5f %.5f")
        np.savetxt(fh, np.repeat(f, 2, axis=1), fmt="f %d/%d/1 %d/%d/1 %d/%d/1")
    return Path(path)
