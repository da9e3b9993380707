"""Checks of a loaded scene that Mitsuba itself does not make (or makes only at render time).

Normal mapping needs two things from a shape that Mitsuba does not verify when it
loads a scene: texture coordinates (a mesh without UVs gets ``uv = 0`` and a
degenerate tangent frame everywhere) and a normal map with three channels (a
one-channel map fails deep inside the JIT at render time), wherever the normal-mapped
BSDF sits (nested in ``twosided``, ``blendbsdf``, ``mask``). And no texture of the scene
may have a uv transform (``to_uv``) that holds NaN or infinity: Mitsuba's bitmap then reads
outside its data (a crash in ``bumpmap``'s gradient, garbage elsewhere). A map decoded in a
mesh's vertex tangents (``tangents="vertex_tangent"``, a MikkTSpace bake) on a shape without them
falls back to Mitsuba's frame: a warning says so.
"""

from __future__ import annotations

import re
import warnings

import mitsuba as mi

__all__ = ["is_normal_mapped", "normal_mapped_shapes", "plugin_instances", "check_scene",
           "missing_tangents"]


def _is_plugin(bsdf) -> bool:
    from mfnormal.plugins.normalmap_microfacet import bsdf_class
    return isinstance(bsdf, bsdf_class())


def is_normal_mapped(bsdf) -> bool:
    """Whether ``bsdf`` is ``normalmap_microfacet`` or Mitsuba's ``normalmap``, or nests one (a
    ``normalmap`` or ``heightmap`` texture among its parameters, as in ``twosided``)."""
    if bsdf is None:
        return False
    if _is_plugin(bsdf) or bsdf.class_name() == "NormalMap":
        return True
    return any({"normalmap", "heightmap"} & set(key.split(".")[:-1]) for key in mi.traverse(bsdf).keys())


def normal_mapped_shapes(scene) -> list:
    return [s for s in scene.shapes() if is_normal_mapped(s.bsdf())]


def plugin_instances(scene) -> list:
    """The ``normalmap_microfacet`` BSDFs of ``scene``, wherever they sit (a shape's BSDF, or
    nested in ``twosided``, ``blendbsdf``, ``mask``): every object of its scene graph."""
    return [obj for obj in mi.traverse(scene).hierarchy if _is_plugin(obj)]


def _shape_name(shape) -> str:
    """``'id' (file)``, ``'file'`` or ``'id'``: how the user can find the shape."""
    sid = shape.id()
    sid = "" if sid in ("", shape.class_name()) else sid
    match = re.search(r'^\s*name = "([^"]+)"', str(shape), re.M) if shape.is_mesh() else None
    file = match.group(1) if match else ""
    if sid and file:
        return f"'{sid}' ({file})"
    return f"'{sid or file or shape.class_name()}'"


def _normalmap_texture(bsdf):
    if _is_plugin(bsdf):
        return bsdf.normalmap
    return None


def _map_channels(bsdf):
    """(channel count, texture name) of the first normal map bitmap in ``bsdf`` (itself or nested
    at any depth: ``normalmap.data`` among its parameters) that does not have 3 channels, or
    (None, None)."""
    params = mi.traverse(bsdf)
    for key in params.keys():
        if not (key == "normalmap.data" or key.endswith(".normalmap.data")):
            continue
        shape = params[key].shape
        channels = shape[-1] if len(shape) == 3 else 1
        if channels != 3:
            names = re.findall(r'name = "([^"]*)"', str(bsdf))
            files = [n for n in names if "." in n]
            return channels, (files[0] if len(files) == 1 else "")
    return None, None


def _evaluates_rgb(tex) -> bool:
    """Whether the texture ``tex`` (None: not the plugin's) can be evaluated as RGB."""
    if tex is None:
        return True
    import drjit as dr
    try:
        tex.eval_3(dr.zeros(mi.SurfaceInteraction3f))
    except Exception:  # noqa: BLE001  (Mitsuba: "Texture::eval_3(): not implemented!")
        return False
    return True


def check_scene(scene, error: type = ValueError, where: str = "") -> None:
    """Raise ``error`` (one line, after ``where: `` when given) for the first normal-mapped
    shape that cannot work: a mesh without UVs, or a normal map that does not have 3 channels;
    or for a texture whose ``to_uv`` is not finite, or a scene without an integrator (Mitsuba
    refuses it only when the render starts). Warns, one line per attribute, where a
    ``normalmap_microfacet`` names vertex tangents its shapes lack (:func:`missing_tangents`)."""
    try:
        if scene.integrator() is None:
            raise ValueError("the scene has no integrator; add one, e.g. <integrator type=\"path\"/> "
                             "(in a scene dict \"integrator\": {\"type\": \"path\"})")
        _check_uv_transforms(scene)
        _check_shapes(scene)
    except ValueError as exc:
        raise error(f"{where}: {exc}" if where else str(exc)) from None
    missing = missing_tangents(scene)
    for attribute in sorted({name for _, name in missing}):
        shapes = [shape for shape, name in missing if name == attribute]
        more = f" (and {len(shapes) - 1} more)" if len(shapes) > 1 else ""
        warnings.warn(f"shape {_shape_name(shapes[0])}{more} has no vertex attribute '{attribute}', which "
                      f"its normalmap_microfacet names (tangents=\"{attribute}\"): its map is decoded in "
                      "Mitsuba's frame instead, wrong for a map baked in MikkTSpace; render it on a mesh "
                      "with the tangents (mfnormal bake --tangent-mesh MESH.ply, or a glTF model)",
                      stacklevel=2)


def missing_tangents(scene) -> list:
    """(shape, attribute) for each shape whose ``normalmap_microfacet`` (its BSDF or nested in it)
    decodes its map in a vertex tangent attribute the shape lacks (it falls back to Mitsuba's
    frame there)."""
    missing = []
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        plugins = [] if bsdf is None else [o for o in mi.traverse(bsdf).hierarchy if _is_plugin(o)]
        if bsdf is not None and _is_plugin(bsdf) and bsdf not in plugins:
            plugins.append(bsdf)
        for name in {p.source.tangents.name for p in plugins if p.source.tangents is not None}:
            if not (shape.is_mesh() and _has_attribute(shape, name)):
                missing.append((shape, name))
    return missing


def _has_attribute(mesh, name: str) -> bool:
    import drjit as dr
    return bool(dr.all(mesh.has_attribute(name), axis=None))


def _check_uv_transforms(scene) -> None:
    from mfnormal.normals.uv import non_finite_uv_transforms, uv_transforms

    owners = [(shape, f"of shape {_shape_name(shape)}") for shape in scene.shapes()]
    for owner, where in owners + [(scene, "of the scene")]:
        for key in non_finite_uv_transforms(uv_transforms(mi.traverse(owner))):
            texture = key[:-len(".to_uv")].rsplit(".", 1)[-1]
            raise ValueError(f"the texture '{texture}' {where} has a uv transform (to_uv) that "
                             "holds NaN or infinity; give its <transform name=\"to_uv\"> finite "
                             "scale, translate and rotate values")


def _check_shapes(scene) -> None:
    from mfnormal.normals.normal_map import channel_count_message

    for shape in normal_mapped_shapes(scene):
        bsdf = shape.bsdf()
        kind = "normalmap_microfacet" if _is_plugin(bsdf) else "normalmap"
        if shape.is_mesh() and not shape.has_vertex_texcoords():
            raise ValueError(f"shape {_shape_name(shape)} has no texture coordinates (UVs), "
                             f"which its {kind} BSDF needs for the normal map and tangent frame")
        channels, name = _map_channels(bsdf)
        if channels is None and not _evaluates_rgb(_normalmap_texture(bsdf)):
            tex = _normalmap_texture(bsdf)
            raise ValueError(f"the normal map of shape {_shape_name(shape)} is a "
                             f"'{tex.class_name()}' texture, which has no RGB evaluation (eval_3); "
                             "a tangent-space normal map needs an RGB texture such as a bitmap")
        if channels is not None and channels != 3:
            what = f"'{name}'" if name else "of shape " + _shape_name(shape)
            raise ValueError(channel_count_message(what, channels))
