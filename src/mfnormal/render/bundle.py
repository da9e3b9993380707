"""A scene as it travels to a cluster's workers (:mod:`mfnormal.render.cluster`).

:func:`scene_spec` reads a scene file on the client: an XML scene's text with every file it names
(``<include>``, ``filename`` and the plugin's ``normalmap`` and ``heightmap``, after ``$``
substitution), or a glTF file with the buffers and images its JSON names; each file is renamed
after its content (:func:`xml_bundle`), so that a worker that has it already keeps it. Nothing
else is read. With ``shared=True`` the workers load the scene from its path (a file system they
share with the client) and nothing travels.
"""

from __future__ import annotations

import hashlib
import json
import re
import urllib.parse
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from mfnormal.io.inputs import FILE_STRINGS
from mfnormal.io.scene_xml import defaults, references, substitute

__all__ = ["SceneSpec", "scene_spec", "xml_bundle", "files_digest", "bundle_name"]


@dataclass(frozen=True)
class SceneSpec:
    """A scene as the workers load it: ``kind`` 'xml' or 'gltf'; ``source`` the XML text,
    the bundle name of the glTF file, or (``shared``) the scene's path; ``params`` the
    ``-D`` values (XML) or :func:`mfnormal.io.gltf.load_gltf` options (glTF); ``files`` the
    digest of the files that travel with it."""
    kind: str
    source: str
    params: tuple = ()
    shared: bool = False
    files: str = ""
    limits: object = None


def bundle_name(data: bytes, name: str) -> str:
    """The name a file travels under: a hash of its content, then its own name made safe."""
    safe = re.sub(r"[^\w.-]", "_", Path(name).name)
    return f"{hashlib.sha256(data).hexdigest()[:16]}_{safe}"


def _add(files: dict, data: bytes, name: str) -> str:
    key = bundle_name(data, name)
    files[key] = data
    return key


def _resolver(folder: Path):
    """Mitsuba's file resolver with ``folder`` searched first (what ``load_file`` uses)."""
    import mitsuba as mi

    current = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    resolver = mi.FileResolver(current)
    resolver.prepend(str(folder))
    return resolver


def _named_file(value: str, resolver) -> Path | None:
    path = Path(str(resolver.resolve(value)))
    return path if path.is_file() else None


def _bundle_tree(root: ET.Element, folder: Path, values: dict, files: dict, depth: int) -> None:
    """Rename, in place, every file ``root`` names to its bundle name (added to ``files``);
    ``<include>``\\ d files are bundled the same way, recursively."""
    resolver = _resolver(folder)
    for el in root.iter():
        attr = "filename" if "filename" in el.attrib else None
        if attr is None and el.tag == "string" and el.get("name") in FILE_STRINGS:
            attr = "value"
        if attr is None:
            continue
        path = _named_file(substitute(el.get(attr), values), resolver)
        if path is None:
            continue                  # not a file: Mitsuba's own error (the client loaded it)
        if el.tag == "include" and depth < 16:
            sub = ET.fromstring(path.read_bytes())
            _bundle_tree(sub, path.parent, {**defaults(sub), **values}, files, depth + 1)
            data = ET.tostring(sub, encoding="utf-8")
        else:
            data = path.read_bytes()
        el.set(attr, _add(files, data, path.name))


def xml_bundle(text: str, folder, params: dict) -> tuple:
    """(XML text, ``-D`` values, files) of the scene ``text`` whose relative file names
    are relative to ``folder``: every file it names (and only those) read into ``files``
    (bundle name → bytes), the text renamed to match; the ``-D`` values it no longer
    uses (those that only named files) dropped."""
    root = ET.fromstring(text)
    files: dict = {}
    _bundle_tree(root, Path(folder).resolve(), {**defaults(root), **params}, files, 0)
    text = ET.tostring(root, encoding="unicode")
    texts = [text] + [d.decode("utf-8", "replace") for k, d in files.items() if k.endswith(".xml")]
    used = {k: v for k, v in params.items() if any(references(t, k) for t in texts)}
    return text, used, files


def _gltf_bundle(path: Path) -> tuple:
    """(bundle name of the glTF file, files): a ``.glb`` alone, or a ``.gltf`` with the
    buffers and images its JSON names by relative URI (renamed to match)."""
    files: dict = {}
    data = path.read_bytes()
    if path.suffix.lower() == ".gltf":
        doc = json.loads(data)
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri")
            if not uri or uri.startswith("data:"):
                continue
            named = path.parent / urllib.parse.unquote(uri)
            if named.is_file():
                item["uri"] = _add(files, named.read_bytes(), named.name)
        data = json.dumps(doc).encode()
    return _add(files, data, path.name), files


def scene_spec(path, params: dict, gltf_options: dict | None = None, shared: bool = False,
               limits=None) -> tuple:
    """(:class:`SceneSpec`, files) of the scene file ``path`` with ``-D`` ``params`` (an XML
    scene) or ``gltf_options`` (a glTF file)."""
    path = Path(path).resolve()
    kind = "xml" if gltf_options is None else "gltf"
    values = params if gltf_options is None else gltf_options
    if shared:
        return SceneSpec(kind, str(path), tuple(sorted(values.items())), True, limits=limits), {}
    if kind == "gltf":
        source, files = _gltf_bundle(path)
    else:
        source, values, files = xml_bundle(path.read_text(encoding="utf-8"), path.parent, params)
    return SceneSpec(kind, source, tuple(sorted(values.items())), False, files_digest(files), limits), files


def files_digest(files: dict) -> str:
    return hashlib.sha256("\0".join(sorted(files)).encode()).hexdigest()[:16]
