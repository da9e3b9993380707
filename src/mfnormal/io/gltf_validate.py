"""Reading and validating a glTF 2.0 file before the loader allocates anything from it.

:func:`read_model` is the only way :mod:`mfnormal.io.gltf` reads a file. It parses
the ``.gltf`` JSON or the ``.glb`` container itself, checks the whole document
against what the loader will do with it, and reads the buffers and images —
each at most what the file declares and what :class:`~mfnormal.io.inputs.Limits`
allows. The loader may then index anything without further checks. Every
violation is a :class:`GLTFError` whose message is one line naming the element,
``nodes[3].children: cycle through node 0``.

What is checked:

- the container: GLB magic, version 2, chunk lengths within the file, JSON
  first; JSON that parses (no NaN/Infinity), an object, ``asset.version`` 2.x;
- types: every property the loader reads has its JSON type and range
  (integers are integers, numbers are finite, enumerations are known values);
- indices: every reference (``bufferView``, ``buffer``, ``mesh``, ``camera``,
  ``material``, ``texture``, ``source``, ``sampler``, ``children``, scene
  ``nodes``, ``KHR_lights_punctual`` ``light``, ``skin``, attributes) is in range;
- the node graph: no cycle, no node with two parents, scene roots are roots;
- data bounds: a bufferView lies inside its buffer; ``byteStride`` is 4–252, a
  multiple of 4 and at least the accessor's element size; an accessor's
  ``byteOffset + stride·(count − 1) + element`` lies inside its bufferView;
  sparse indices and values lie inside theirs (and the index values inside the
  accessor, checked when read); an accessor without a bufferView (zeros) counts
  against the byte budget; mesh attributes have the types the loader reads and
  the same count as ``POSITION``;
- URIs: ``data:`` (base64) or a relative path that resolves (symbolic links
  followed) inside the model's folder, to a regular file, of at least the
  declared ``byteLength`` (and only that much is read); nothing else is opened;
- sizes: the file, buffers and image files together at most ``data_bytes``;
  each image's width × height (from its PNG/JPEG header, before decoding) at
  most ``image_pixels``, all of them at most ``texture_pixels``; the vertices
  of the default scene after instancing at most ``vertices``;
- cameras (``yfov`` in (0, π), ``znear`` > 0, ``zfar`` > ``znear``,
  ``aspectRatio`` > 0, ``xmag``/``ymag`` non-zero), lights (known type, colour
  and intensity ≥ 0, ``range`` > 0, 0 ≤ inner < outer ≤ π/2 cone angles),
  material factors in [0, 1], node matrices, translations, rotations (non-zero
  quaternions; normalised) and scales finite.

The parts: :mod:`~mfnormal.io.gltf_container` (the container, URIs, the byte budget),
:mod:`~mfnormal.io.gltf_json` (the JSON, typed getters, :class:`GLTFError`),
:mod:`~mfnormal.io.gltf_check_data` (buffers, accessors, meshes) and
:mod:`~mfnormal.io.gltf_check_scene` (textures, materials, cameras, lights, nodes, scenes).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from mfnormal.io.gltf_check_data import (COMPONENT_SIZE, TYPE_WIDTH, check_accessors, check_buffers_and_views,
                                         check_meshes)
from mfnormal.io.gltf_check_scene import (check_cameras, check_instanced_vertices, check_materials, check_nodes,
                                          check_punctual_lights, check_samplers_textures_images, check_scenes)
from mfnormal.io.gltf_container import Budget, ImageData, read_buffers, read_container, read_images
from mfnormal.io.gltf_json import Document, GLTFError, decode_error, fail, parse_json, show  # noqa: F401
from mfnormal.io.image_headers import image_header  # noqa: F401
from mfnormal.io.inputs import DEFAULT_LIMITS, Limits

__all__ = ["GLTFError", "Model", "ImageData", "read_model", "image_header", "COMPONENT_SIZE",
           "TYPE_WIDTH"]


@dataclass
class Model:
    """A validated glTF file: its JSON text and document, buffers (each exactly its
    ``byteLength``), images and the index of every node's parent (None for roots)."""
    path: Path
    text: str
    doc: dict
    buffers: list = field(default_factory=list)
    images: list = field(default_factory=list)
    parents: list = field(default_factory=list)
    scene_roots: list = field(default_factory=list)


def check_asset(gltf: Document) -> None:
    """The document's ``asset`` (a glTF 2.x version, a ``minVersion`` of at most 2.0) and its
    lists of the extensions it uses and requires."""
    asset = gltf.obj(gltf.doc, "asset", "", required=True)
    version = gltf.string(asset, "version", "asset")
    if version is None or not re.fullmatch(r"2\.\d+", version):
        fail("asset.version", f"{show(version)} is not a glTF 2.x version")
    minimum = gltf.string(asset, "minVersion", "asset")
    if minimum is not None and not re.fullmatch(r"2\.0", minimum):
        fail("asset.minVersion", f"'{minimum}' is newer than the glTF 2.0 this loader reads")
    for key in ("extensionsUsed", "extensionsRequired"):
        v = gltf.doc.get(key, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            fail(key, f"expected an array of strings, got {show(v)}")


def _required_extensions(doc: dict) -> None:
    """A :class:`GLTFError` where the file requires compressed geometry (not supported)."""
    unsupported = {"KHR_draco_mesh_compression", "EXT_meshopt_compression",
                   "KHR_mesh_quantization"} & set(doc.get("extensionsRequired") or [])
    if unsupported:
        raise GLTFError(f"needs {', '.join(sorted(unsupported))}, which is not supported")


def read_model(path, limits: Limits = DEFAULT_LIMITS) -> Model:
    """Read and validate the glTF 2.0 file ``path``: see the module docstring. Raises
    :class:`GLTFError` (one line) for anything the loader cannot use safely."""
    path = Path(path)
    budget = Budget(limits)
    text, binary = read_container(path, budget)
    doc = parse_json(text)
    gltf = Document(doc, limits)
    check_asset(gltf)
    _required_extensions(doc)
    check_buffers_and_views(gltf)
    check_accessors(gltf, budget)
    check_samplers_textures_images(gltf)
    check_materials(gltf)
    check_meshes(gltf)
    check_cameras(gltf)
    check_punctual_lights(gltf)
    parents = check_nodes(gltf)
    roots = check_scenes(gltf, parents)
    check_instanced_vertices(gltf, roots)

    model = Model(path, text, doc, parents=parents, scene_roots=roots)
    model.buffers = read_buffers(gltf.arrays["buffers"], binary, path.parent, budget)
    model.images = read_images(gltf.arrays["images"], gltf.arrays["bufferViews"], model.buffers, path.parent,
                               budget, limits)
    return model
