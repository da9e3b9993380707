"""The bundled scenes and their procedural assets (nothing is downloaded).

:data:`BUNDLED` names the six scenes ``mfnormal compare`` knows: each is an XML
file in ``scenes/``, a function that writes its assets into a folder and one that
turns their paths into the scene's ``$`` parameters.

- (a) ``demo`` (:data:`DEMO_XML`, :mod:`mfnormal.cli.demo`): a gold sphere and a tiled
  ground plane; :func:`make_tiles_normalmap`, a strong normal map of pillowed tiles
  with a hemispherical rivet in each;
- (b) ``model`` (:data:`MODEL_XML`), the counterpart of the supplemental's Figures 3
  and 5 (strong normal-mapped detail, varying roughness, grazing angles):
  :func:`torus_knot_mesh`, a (2, 3) torus knot tube of 20,000 triangles with smooth
  vertex normals and a seamless UV parametrisation (u along the knot, v around the
  tube, one UV unit ≈ one tube circumference in both directions);
  :func:`make_domes_normalmap`, a hexagonal array of spherical domes whose rims tilt
  to 70°; :func:`make_roughness_map`, GGX α in [0.04, 0.45] in soft bands along the knot;
- (c) ``eggcrate`` (:data:`EGGCRATE_XML`): glossy metal at grazing view;
  :func:`make_eggcrate_normalmap`;
- (d) ``water`` (:data:`WATER_XML`): a rippled water surface (``dielectric``, ior 1.33) over
  a checkerboard floor: :func:`make_ripples_normalmap`, a periodic sum of waves;
- (e) ``glass`` (:data:`GLASS_XML`): a sphere of hammered glass (``dielectric``, ior 1.5, the
  dome map of scene (b) with rims at 35°) on the same floor;
- (f) ``underwater`` (:data:`UNDERWATER_XML`): the water of scene (d) seen from below, looking
  up 40° from the vertical through Snell's window and beyond it, where the surface reflects the
  floor totally.

Every scene is lit by the sky of :mod:`mfnormal.scenes.sky` (:data:`mfnormal.scenes.sky.DEMO` with
a sun). Normal maps are written as 8-bit PNGs (:func:`encode_normalmap`), OpenGL
convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mfnormal.scenes import sky
from mfnormal.files import atomic_write

__all__ = ["BUNDLED", "Bundled", "DEMO_XML", "MODEL_XML", "EGGCRATE_XML", "encode_normalmap",
           "make_tiles_normalmap", "generate_demo_assets", "torus_knot_mesh", "write_ply",
           "make_domes_normalmap", "make_roughness_map", "generate_model_assets",
           "model_parameters", "make_eggcrate_normalmap", "generate_eggcrate_assets",
           "file_parameters", "map_and_sky_parameters", "WATER_XML", "make_ripples_normalmap",
           "generate_water_assets", "GLASS_XML", "generate_glass_assets", "UNDERWATER_XML"]

SCENES = Path(__file__).resolve().parent
#: Scene (a): the demo (single source of truth).
DEMO_XML = SCENES / "demo.xml"
#: Scene (b): the model scene.
MODEL_XML = SCENES / "model.xml"
#: Scene (c): the egg crate at grazing view.
EGGCRATE_XML = SCENES / "eggcrate.xml"
#: Scene (d): water over a floor.
WATER_XML = SCENES / "water.xml"
#: Scene (e): a hammered glass sphere.
GLASS_XML = SCENES / "glass.xml"
#: Scene (f): the water of scene (d) seen from below.
UNDERWATER_XML = SCENES / "underwater.xml"

TILES_NAME = "normalmap.png"
MESH_NAME = "knot.ply"
EGGCRATE_NAME = "eggcrate.png"
RIPPLES_NAME = "ripples.png"
HAMMERED_NAME = "hammered.png"
DOMES_NAME = "domes.png"
ROUGHNESS_NAME = "roughness.exr"
ENVMAP_NAME = "envmap.exr"


# ---------------------------------------------------------------------------
# Writing textures
# ---------------------------------------------------------------------------

def encode_normalmap(n: np.ndarray) -> np.ndarray:
    """8-bit encoding rgb = n * 0.5 + 0.5."""
    return np.clip(np.round((n * 0.5 + 0.5) * 255.0), 0, 255).astype(np.uint8)



def _write_png(path, normals: np.ndarray):
    """Unit normals as an 8-bit PNG (:func:`encode_normalmap`), atomically."""
    import mitsuba as mi

    bitmap = mi.Bitmap(encode_normalmap(normals))
    atomic_write(path, lambda p: bitmap.write(str(p), mi.Bitmap.FileFormat.PNG))


def _write_exr(path, pixels: np.ndarray, pixel_format: str = "RGB"):
    import mitsuba as mi

    bitmap = mi.Bitmap(pixels, getattr(mi.Bitmap.PixelFormat, pixel_format))
    atomic_write(path, lambda p: bitmap.write(str(p), mi.Bitmap.FileFormat.OpenEXR))


def _write_sky(path, sun: sky.GlowSun = sky.GlowSun()):
    """The bundled scenes' sky (256 × 128) with ``sun``, as an EXR."""
    _write_exr(path, sky.envmap(256, 128, sky.DEMO, sun))


def file_parameters(assets: dict, names) -> dict:
    """The ``$name`` parameters ``names`` of a scene: the absolute paths of its generated files."""
    return {k: str(Path(assets[k]).resolve()) for k in names}


# ---------------------------------------------------------------------------
# Scene (a): the demo
# ---------------------------------------------------------------------------

def make_tiles_normalmap(size: int = 512, tiles: int = 4, gap: float = 0.035,
                   bevel: float = 0.2, rivet: float = 0.2) -> np.ndarray:
    """Unit tangent-space normals (``size`` x ``size`` x 3, float32).

    A running-bond pattern of ``tiles`` x ``tiles`` square tiles separated by
    flat grooves; each tile has a quarter-circle bevel (its normals tilt all the
    way to the horizon at the tile border) and a hemispherical rivet in its
    centre. The pattern is periodic, so the map tiles seamlessly. All lengths
    are in units of one tile.

    OpenGL convention: +x points right and +y *up* in the image (row 0 is the
    top row), so a bump looks green at its top and red at its right side.
    """
    c = (np.arange(size, dtype=np.float64) + 0.5) * (tiles / size)
    x, y = np.meshgrid(c, c)                     # y grows downwards (rows)
    row = np.floor(y)
    xs = x + 0.5 * (row % 2)                     # offset every other row
    px = xs - np.floor(xs) - 0.5                 # position within the tile,
    py = y - row - 0.5                           # in [-0.5, 0.5)
    half = 0.5 - gap / 2

    # Bevel: distance to the inner (flat-topped) rectangle, rounded corners.
    mx = np.maximum(np.abs(px) - (half - bevel), 0.0)
    my = np.maximum(np.abs(py) - (half - bevel), 0.0)
    d = np.hypot(mx, my)
    s = np.clip(d / bevel, 0.0, 1.0)             # sin of the tilt
    inv_d = np.where(d > 0, 1.0 / np.maximum(d, 1e-12), 0.0)
    nx = s * mx * inv_d * np.sign(px)
    ny = -s * my * inv_d * np.sign(py)           # image y is down, normal y up
    nz = np.sqrt(np.maximum(1.0 - s * s, 0.0))

    in_groove = (np.abs(px) > half) | (np.abs(py) > half)
    nx[in_groove], ny[in_groove], nz[in_groove] = 0.0, 0.0, 1.0

    # Hemispherical rivet.
    r2 = px * px + py * py
    on_rivet = r2 < rivet * rivet
    nx = np.where(on_rivet, px / rivet, nx)
    ny = np.where(on_rivet, -py / rivet, ny)
    nz = np.where(on_rivet, np.sqrt(np.maximum(rivet * rivet - r2, 0.0)) / rivet, nz)

    n = np.stack([nx, ny, nz], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def generate_demo_assets(assets_dir) -> dict:
    """Write the demo's textures into ``assets_dir``; returns their paths as
    ``{'normalmap': Path, 'envmap': Path}``. Deterministic and fast (well under a
    second), so the files are simply rewritten every time."""
    assets_dir = Path(assets_dir)
    paths = {"normalmap": assets_dir / TILES_NAME, "envmap": assets_dir / ENVMAP_NAME}
    _write_png(paths["normalmap"], make_tiles_normalmap())
    _write_sky(paths["envmap"])
    return paths


# ---------------------------------------------------------------------------
# Scene (b): the torus knot
# ---------------------------------------------------------------------------

def _knot_curve(t, p=2, q=3, R=1.0, a=0.42):
    """Points on a (p, q) torus knot around the y axis (y up)."""
    r = R + a * np.cos(q * t)
    return np.stack([r * np.cos(p * t), a * np.sin(q * t), r * np.sin(p * t)], axis=-1)


def _rotation_minimizing_frames(c):
    """Normals of a rotation-minimising frame along the closed polyline ``c``
    (double reflection, Wang et al. 2008), with the holonomy spread evenly so
    the frame closes up."""
    n = len(c)
    tangent = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    seed = np.cross(tangent[0], [0.0, 1.0, 0.0])
    r = np.empty_like(c)
    r[0] = seed / np.linalg.norm(seed)
    for i in range(n):
        j = (i + 1) % n
        v1 = c[j] - c[i]
        r_l = r[i] - 2.0 * v1 * (v1 @ r[i]) / (v1 @ v1)
        t_l = tangent[i] - 2.0 * v1 * (v1 @ tangent[i]) / (v1 @ v1)
        v2 = tangent[j] - t_l
        r_next = r_l - 2.0 * v2 * (v2 @ r_l) / max(v2 @ v2, 1e-30)
        if j == 0:
            closing = r_next
        else:
            r[j] = r_next
    # Twist the frames so that the last one meets the first.
    b0 = np.cross(tangent[0], r[0])
    twist = np.arctan2(closing @ b0, closing @ r[0])
    angle = -twist * np.arange(n) / n
    b = np.cross(tangent, r)
    r = np.cos(angle)[:, None] * r + np.sin(angle)[:, None] * b
    return tangent, r, np.cross(tangent, r)


def torus_knot_mesh(n_u: int = 400, n_v: int = 25, tube: float = 0.27, lift: float = 0.74):
    """The torus knot tube: ``(positions, normals, uvs, faces)`` as numpy arrays.

    ``2 n_u n_v`` triangles (20,000 by default). The tube radius swells by ±15 %
    along the knot. Seams are duplicated vertices with identical positions and
    normals, so shading is continuous and the UVs are seamless: u runs over
    ``[0, U]`` along the knot with U the (integer) number of tube circumferences
    in its length, v over ``[1, 0]`` around the tube. Mitsuba's tangent frame is
    s ∥ dp/du, t = n × s, and t points toward decreasing v, which is image up in
    Mitsuba's bitmaps (v = 0 is the top row): the OpenGL convention. The knot
    rests on the plane y = 0.
    """
    t = 2.0 * np.pi * np.arange(n_u) / n_u
    c = _knot_curve(t)
    _, r, b = _rotation_minimizing_frames(c)
    rho = tube * (1.0 + 0.15 * np.cos(5.0 * t))[:, None, None]
    phi = 2.0 * np.pi * np.arange(n_v) / n_v
    # The minus sign makes v turn so that dp/du x dp/dv points outwards.
    ring = (np.cos(phi)[None, :, None] * r[:, None, :]
            - np.sin(phi)[None, :, None] * b[:, None, :])
    p = c[:, None, :] + rho * ring                           # (n_u, n_v, 3), periodic

    # Smooth normals from central differences on the periodic grid.
    dpu = np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)
    dpv = np.roll(p, -1, axis=1) - np.roll(p, 1, axis=1)
    nrm = np.cross(dpu, dpv)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    if np.mean(np.sum(nrm * ring, axis=-1)) < 0:
        raise AssertionError("torus knot normals point inwards")

    # Close the grid with duplicated seam vertices.
    idx_u = np.arange(n_u + 1) % n_u
    idx_v = np.arange(n_v + 1) % n_v
    P = p[idx_u][:, idx_v]
    N = nrm[idx_u][:, idx_v]
    length = np.sum(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1))
    u_max = max(1, int(round(length / (2.0 * np.pi * tube))))
    # v runs backwards: Mitsuba's bitmaps put v = 0 on the top row, and the normal
    # map's +y (image up) must be the frame's t = n x dp/du.
    uu, vv = np.meshgrid(np.linspace(0.0, u_max, n_u + 1), np.linspace(1.0, 0.0, n_v + 1),
                         indexing="ij")
    UV = np.stack([uu, vv], axis=-1)

    P = P.reshape(-1, 3).copy()
    P[:, 1] += lift
    N = N.reshape(-1, 3)
    UV = UV.reshape(-1, 2)
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    v00 = (i * (n_v + 1) + j).ravel()
    v10, v01 = v00 + (n_v + 1), v00 + 1
    v11 = v10 + 1
    F = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return (P.astype(np.float32), N.astype(np.float32), UV.astype(np.float32),
            F.astype(np.int32))


def write_ply(path, positions, normals, uvs, faces) -> Path:
    """Binary little-endian PLY with per-vertex normals and UVs (``u``, ``v``)."""
    vert = np.empty(len(positions), dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
    for k, col in zip(("x", "y", "z"), positions.T):
        vert[k] = col
    for k, col in zip(("nx", "ny", "nz"), normals.T):
        vert[k] = col
    vert["u"], vert["v"] = uvs[:, 0], uvs[:, 1]
    face = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, faces
    header = ("ply\nformat binary_little_endian 1.0\ncomment mfnormal torus knot\n"
              f"element vertex {len(vert)}\n"
              + "".join(f"property float {k}\n" for k in vert.dtype.names)
              + f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n")

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(vert.tobytes())
            f.write(face.tobytes())
    return atomic_write(path, write)


# ---------------------------------------------------------------------------
# Textures
# ---------------------------------------------------------------------------

def make_domes_normalmap(size: int = 512, columns: int = 7, rows: int = 4,
                         radius: float = 0.46, rim_tilt_deg: float = 70.0) -> np.ndarray:
    """Unit tangent-space normals (``size`` x ``size`` x 3, float32) of a
    hexagonal array of spherical domes on a flat plate.

    ``columns`` domes per row, ``2 rows`` rows (hexagonal rows are √3/2 apart,
    so 7 x 4·√3 ≈ 7 x 6.93 keeps the domes round within 1 %). Each dome is a
    spherical cap of footprint ``radius`` (units of the dome spacing) whose rim
    tilts to ``rim_tilt_deg``. OpenGL convention (+y up in the image).
    """
    height = 2.0 * rows * np.sqrt(3.0) / 2.0
    x, y = np.meshgrid((np.arange(size) + 0.5) * columns / size,
                       (np.arange(size) + 0.5) * height / size)
    # Nearest centre among the two rectangular sub-lattices of the hexagonal one.
    best = None
    for ox, oy in ((0.0, 0.0), (0.5, np.sqrt(3.0) / 2.0)):
        gy = np.sqrt(3.0)
        dx = x - ox - np.round(x - ox)
        dy = y - oy - gy * np.round((y - oy) / gy)
        d2 = dx * dx + dy * dy
        best = (dx, dy, d2) if best is None else tuple(np.where(d2 < best[2], a, b)
                                                       for a, b in zip((dx, dy, d2), best))
    dx, dy, d2 = best
    sphere_r = radius / np.sin(np.radians(rim_tilt_deg))
    inside = d2 < radius * radius
    nz = np.sqrt(np.maximum(sphere_r * sphere_r - d2, 0.0))
    n = np.stack([np.where(inside, dx, 0.0), np.where(inside, -dy, 0.0),   # image y is down
                  np.where(inside, nz, 1.0)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def make_roughness_map(width: int = 512, height: int = 16, bands: int = 7,
                       alpha_min: float = 0.04, alpha_max: float = 0.45) -> np.ndarray:
    """GGX α (``height`` x ``width`` x 1, float32): ``bands`` soft polished/rough
    bands along u, with a gentle ripple around v. Periodic in u and v."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    s = 0.5 + 0.5 * np.sin(2.0 * np.pi * (bands * uu + 0.15 * np.sin(2.0 * np.pi * vv)))
    s = s * s * (3.0 - 2.0 * s)                        # smoothstep: sharper transitions
    alpha = alpha_min + (alpha_max - alpha_min) * s
    return alpha[..., None].astype(np.float32)


def generate_model_assets(assets_dir) -> dict:
    """Write the mesh and textures of scene (b) into ``assets_dir``; returns
    ``{'mesh', 'normalmap', 'roughness', 'envmap', 'u_max'}`` (paths and the
    knot's UV length). Deterministic; rewritten every time (≈ 0.5 s)."""
    assets_dir = Path(assets_dir)
    P, N, UV, F = torus_knot_mesh()
    paths = {"mesh": assets_dir / MESH_NAME, "normalmap": assets_dir / DOMES_NAME,
             "roughness": assets_dir / ROUGHNESS_NAME, "envmap": assets_dir / ENVMAP_NAME}
    write_ply(paths["mesh"], P, N, UV, F)
    _write_png(paths["normalmap"], make_domes_normalmap())
    _write_exr(paths["roughness"], make_roughness_map(), "Y")
    _write_sky(paths["envmap"])
    paths["u_max"] = float(UV[:, 0].max())
    return paths


def model_parameters(assets: dict) -> dict:
    """The ``$name`` substitutions of :data:`MODEL_XML` for generated ``assets``."""
    params = file_parameters(assets, ("mesh", "normalmap", "roughness", "envmap"))
    params["roughness_scale"] = repr(1.0 / float(assets["u_max"]))
    return params


# ---------------------------------------------------------------------------
# Scene (c): the egg crate
# ---------------------------------------------------------------------------

def make_eggcrate_normalmap(size: int = 256, cells: int = 4, max_tilt_deg: float = 70.0) -> np.ndarray:
    """Unit normals (``size`` x ``size`` x 3, OpenGL convention) of the egg crate
    h = A·sin(2πk x)·sin(2πk y), k = ``cells``, whose steepest slope is ``max_tilt_deg``.
    Periodic: it tiles."""
    c = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(c, 1.0 - c)                     # image row 0 is the top (v = 0), +y up
    w = 2.0 * np.pi * cells
    amp = np.tan(np.radians(max_tilt_deg)) / w         # max |∇h| = A·w (at sin·cos = 1 on an axis)
    hx = amp * w * np.cos(w * x) * np.sin(w * y)
    hy = amp * w * np.sin(w * x) * np.cos(w * y)
    n = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def generate_eggcrate_assets(assets_dir) -> dict:
    """Write the textures of scene (c) into ``assets_dir``; returns ``{'normalmap', 'envmap'}``."""
    assets_dir = Path(assets_dir)
    paths = {"normalmap": assets_dir / EGGCRATE_NAME, "envmap": assets_dir / ENVMAP_NAME}
    _write_png(paths["normalmap"], make_eggcrate_normalmap())
    # The sun 20° up, ahead of the camera and to its left: glints off slopes facing back.
    _write_sky(paths["envmap"], sky.GlowSun(direction=(-0.5, 0.34, -0.8)))
    return paths


# ---------------------------------------------------------------------------
# Scene (d): water
# ---------------------------------------------------------------------------

#: The ripples' waves: (cycles along x, cycles along y, relative amplitude, phase) over the map.
RIPPLE_WAVES = ((3, 1, 1.0, 0.3), (-2, 3, 0.7, 1.9), (5, -2, 0.45, 4.1), (1, 6, 0.35, 2.6),
                (-7, -4, 0.2, 0.8), (9, 5, 0.12, 5.3))


def make_ripples_normalmap(size: int = 256, max_tilt_deg: float = 25.0) -> np.ndarray:
    """Unit normals (``size`` x ``size`` x 3, OpenGL convention) of wind ripples: the height field
    ``Σ a cos(2π (k_x x + k_y y) + φ)`` of :data:`RIPPLE_WAVES` (integer wave numbers: the map
    tiles), scaled so that its steepest slope is ``max_tilt_deg``."""
    c = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(c, 1.0 - c)                     # image row 0 is the top (v = 0), +y up
    hx, hy = np.zeros_like(x), np.zeros_like(x)
    for kx, ky, a, phi in RIPPLE_WAVES:
        d = -2.0 * np.pi * a * np.sin(2.0 * np.pi * (kx * x + ky * y) + phi)
        hx += kx * d
        hy += ky * d
    scale = np.tan(np.radians(max_tilt_deg)) / np.hypot(hx, hy).max()
    n = np.stack([-scale * hx, -scale * hy, np.ones_like(hx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def generate_water_assets(assets_dir) -> dict:
    """Write the textures of scene (d) into ``assets_dir``; returns ``{'normalmap', 'envmap'}``
    (the sky without a sun: a small bright sun seen through a smooth surface from a diffuse
    floor is a caustic, which a path tracer finds only by chance)."""
    assets_dir = Path(assets_dir)
    paths = {"normalmap": assets_dir / RIPPLES_NAME, "envmap": assets_dir / ENVMAP_NAME}
    _write_png(paths["normalmap"], make_ripples_normalmap())
    _write_exr(paths["envmap"], sky.envmap(256, 128, sky.DEMO))
    return paths


def generate_glass_assets(assets_dir) -> dict:
    """Write the textures of scene (e) into ``assets_dir``: the hammered-glass dome map (rims at
    35°) and the sky without a sun (see :func:`generate_water_assets`)."""
    assets_dir = Path(assets_dir)
    paths = {"normalmap": assets_dir / HAMMERED_NAME, "envmap": assets_dir / ENVMAP_NAME}
    _write_png(paths["normalmap"], make_domes_normalmap(rim_tilt_deg=35.0))
    _write_exr(paths["envmap"], sky.envmap(256, 128, sky.DEMO))
    return paths


# ---------------------------------------------------------------------------
# The bundled scenes
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Bundled:
    """A bundled scene: its XML file, title, asset generator and ``$`` parameters of the assets."""
    name: str
    xml: Path
    title: str
    generate: Callable        # generate(assets_dir) -> {name: path, ...}
    parameters: Callable      # parameters(assets) -> {"$name": value}


def map_and_sky_parameters(assets: dict) -> dict:
    """The ``$normalmap`` and ``$envmap`` of scenes (a), (c), (d), (e) and (f) for generated ``assets``."""
    return file_parameters(assets, ("normalmap", "envmap"))


BUNDLED = {b.name: b for b in (
    Bundled("demo", DEMO_XML, "(a) demo: sphere and ground plane", generate_demo_assets,
            map_and_sky_parameters),
    Bundled("model", MODEL_XML, "(b) model: torus knot with textured roughness",
            generate_model_assets, model_parameters),
    Bundled("eggcrate", EGGCRATE_XML, "(c) egg crate: glossy metal at 78° from the vertical",
            generate_eggcrate_assets, map_and_sky_parameters),
    Bundled("water", WATER_XML, "(d) water: rippled water over a tiled floor", generate_water_assets,
            map_and_sky_parameters),
    Bundled("glass", GLASS_XML, "(e) glass: a hammered glass sphere on a tiled floor", generate_glass_assets,
            map_and_sky_parameters),
    Bundled("underwater", UNDERWATER_XML, "(f) underwater: the rippled water seen from below",
            generate_water_assets, map_and_sky_parameters),
)}
