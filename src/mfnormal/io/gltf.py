"""glTF 2.0 scenes (``.gltf``, ``.glb``) as Mitsuba scenes, normal maps decoded in the baker's frame.

:func:`load_gltf` reads a file with ``pygltflib`` and returns a Mitsuba scene
dict: one triangle mesh per primitive and node (in world space), its material as
a ``principled`` BSDF (base colour, metallic, roughness, with their textures and
factors) wrapped in ``normalmap_microfacet`` where the material has a
``normalTexture`` (its ``scale`` is the plugin's ``strength``), the file's first
camera or one that frames the model, and its ``KHR_lights_punctual`` lights or
a generated sky with a sun.

Tangent frames: normal maps are baked in MikkTSpace. Each normal-mapped mesh
carries the per-vertex tangent T (attribute ``vertex_tangent``) and the
handedness sign (``vertex_tangent_sign``, glTF's ``TANGENT.w``): the file's
``TANGENT`` where it has one, else MikkTSpace tangents computed here
(:mod:`mfnormal.normals.mikktspace`; vertices are split where they differ), and the
plugin decodes the map in T, B = sign·(N×T), N (its ``tangents`` parameter).

Texture conventions: base colour is sRGB, normals and metallic-roughness are
linear (roughness in G, metallic in B). glTF's UV origin is the image's top
left, which is also where Mitsuba's ``bitmap`` puts v = 0, so UVs pass through
unchanged; MikkTSpace tangents are computed for (u, 1 − v), whose +v is the
image's up, the normal map's +Y.

Hostile files: :func:`mfnormal.io.gltf_validate.read_model` reads and validates the
whole file first (the node graph, every index, buffer bounds, URIs confined to
the model's folder, sizes against :class:`mfnormal.io.inputs.Limits`); what it
refuses is a :class:`GLTFError`, one line naming the element. A degenerate
transform (a zero scale) skips that mesh, light or camera with a warning.

Not supported (ignored, with a warning): texture coordinate sets other than
``TEXCOORD_0``, ``KHR_texture_transform``, emission, occlusion, alpha
blending and masking, skins, morph targets, animation, compressed geometry
(Draco, meshopt: an error) and the ``KHR_materials_*`` extensions.

The loader's parts: :mod:`~mfnormal.io.gltf_arrays` (accessors and images as arrays),
:mod:`~mfnormal.io.gltf_geometry` (nodes and primitives in world space),
:mod:`~mfnormal.io.gltf_materials` (BSDFs), :mod:`~mfnormal.io.gltf_view` (camera and lights),
:mod:`mfnormal.io.meshes` (the Mitsuba meshes); this module puts the scene together.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mfnormal.io.gltf_arrays import GLTFFile
from mfnormal.io.gltf_geometry import FAN, STRIP, TRIANGLES, is_smooth_shaded, primitive_arrays, to_world, walk_nodes
from mfnormal.io.gltf_materials import Materials
from mfnormal.io.gltf_validate import GLTFError
from mfnormal.io.gltf_view import check_render_size, scene_emitters, scene_sensor
from mfnormal.io.inputs import DEFAULT_LIMITS, Limits
from mfnormal.io.meshes import mitsuba_mesh

__all__ = ["load_gltf", "GLTF_SUFFIXES", "TANGENT_MODES", "MACRO_NORMALS", "GLTFError", "is_smooth_shaded",
           "mitsuba_mesh"]

GLTF_SUFFIXES = (".gltf", ".glb")
TANGENT_MODES = ("auto", "mikktspace", "mitsuba")
#: ``load_gltf(macro_normal=...)``: ``shading`` (the interpolated normal is the macro surface, as
#: without the option) or ``geometric`` (every smooth-shaded mesh gets the true triangle as the
#: macro surface: ``normalmap_microfacet`` with ``macro_normal="geometric"``, map or not).
MACRO_NORMALS = ("shading", "geometric")


def _meshes(f: GLTFFile, materials: Materials, nodes, tangents: str, macro_normal: str):
    """({shape id: Mitsuba mesh}, lo, hi): every triangle primitive of the scene's nodes in
    world space, and their bounding box; one BSDF per (material, uv, tangents, smooth-shaded under
    ``macro_normal="geometric"``) shared by its meshes."""
    import mitsuba as mi

    gltf, shapes, bsdfs = f.gltf, {}, {}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for i, node, world in nodes:
        if node.skin is not None:
            materials.warn_once("skin", "skins are ignored (meshes are rendered in bind pose)")
        if node.mesh is None:
            continue
        mesh = gltf.meshes[node.mesh]
        for k, prim in enumerate(mesh.primitives):
            if prim.mode not in (None, TRIANGLES, STRIP, FAN):
                materials.warn_once(("mode", prim.mode), f"primitive mode {prim.mode} (points/lines) "
                                                         "is skipped")
                continue
            if prim.attributes.POSITION is None:
                continue
            if prim.targets:
                materials.warn_once("morph", "morph targets are ignored")
            want = materials.wants_tangents(prim.material)
            where = f"meshes[{node.mesh}].primitives[{k}]"
            positions, normals, uvs, tan, faces = primitive_arrays(f, prim, want, tangents, where)
            if len(faces) == 0:
                continue
            placed = to_world(world, positions, normals, tan, faces, f"nodes[{i}]")
            if placed is None:
                continue
            positions, normals, tan, faces = placed
            smooth = macro_normal == "geometric" and is_smooth_shaded(positions, normals, faces)
            key = (prim.material, uvs is not None, tan is not None, smooth)
            if key not in bsdfs:
                bsdfs[key] = mi.load_dict(materials.bsdf(prim.material, uvs is not None, tan is not None, smooth))
            name = f"{mesh.name or f'mesh{node.mesh}'}/{k}"
            shapes[f"mesh_{len(shapes)}"] = mitsuba_mesh(name, bsdfs[key], positions, normals, uvs,
                                                          tan, faces)
            lo = np.minimum(lo, positions.min(axis=0))
            hi = np.maximum(hi, positions.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise GLTFError("the default scene has no triangle meshes")
    with np.errstate(over="ignore", invalid="ignore"):
        if not np.all(np.isfinite(hi - lo)) or not np.isfinite(np.linalg.norm(hi - lo)):
            raise GLTFError("the model's extent overflows the float range")
    return shapes, lo, hi


def load_gltf(path, *, width: int = 640, height: int = 480, spp: int = 64, max_depth: int = 8,
              model: str = "faithful", tangents: str = "auto", normal_maps: bool = True,
              lights: bool = True, macro_normal: str = "shading", limits: Limits = DEFAULT_LIMITS) -> dict:
    """A Mitsuba scene dict of the glTF 2.0 file ``path`` (``.gltf`` or ``.glb``).

    Needs an active Mitsuba variant (the meshes are built in it). Options:
    ``width``, ``height``, ``spp``, ``max_depth`` (path tracer); ``model``: the
    ``normalmap_microfacet`` model; ``tangents``: ``auto`` (the file's
    ``TANGENT``, else MikkTSpace), ``mikktspace`` (always computed) or
    ``mitsuba`` (Mitsuba's per-triangle frame, for comparison);
    ``normal_maps=False`` drops the normal maps; ``lights=False`` ignores the
    file's lights for the generated sky; ``macro_normal``: ``shading`` (default) or
    ``geometric``: every smooth-shaded mesh (:func:`is_smooth_shaded`) gets the true triangle
    as its microsurface's macro normal, its interpolated normal (and normal map, if any) as the
    facet: ``normalmap_microfacet`` with ``macro_normal="geometric"``, wrapping also the
    materials without a normal map (the shadow-terminator fix; flat-shaded meshes are left
    as they are); ``limits``: the caps on what the file
    may make the loader allocate (:class:`mfnormal.io.inputs.Limits`).

    The file is validated first (:mod:`mfnormal.io.gltf_validate`); anything the
    loader cannot use safely raises :class:`GLTFError`, one line naming the
    element. Files are read only from the model's own folder.
    """
    import mfnormal

    if tangents not in TANGENT_MODES:
        raise ValueError(f"tangents must be one of {', '.join(TANGENT_MODES)}, got '{tangents}'")
    if macro_normal not in MACRO_NORMALS:
        raise ValueError(f"macro_normal must be one of {', '.join(MACRO_NORMALS)}, got '{macro_normal}'")
    for name, value, lo in (("width", width, 1), ("height", height, 1), ("spp", spp, 1),
                            ("max_depth", max_depth, -1)):
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value < 1 << 31:
            raise GLTFError(f"{name} must be an integer from {lo} to {(1 << 31) - 1}, got {value!r}")
    check_render_size(width, height, limits, "the film (width, height)")
    mfnormal.register()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"glTF file not found: {path}")
    f = GLTFFile(path, limits)
    nodes = list(walk_nodes(f.gltf, f.model.scene_roots))
    shapes, lo, hi = _meshes(f, Materials(f, model, tangents, normal_maps, macro_normal), nodes, tangents,
                             macro_normal)
    return {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}, **shapes,
            "sensor": scene_sensor(f.gltf, nodes, lo, hi, width, height, spp, limits),
            **scene_emitters(f.gltf, nodes, lights)}
