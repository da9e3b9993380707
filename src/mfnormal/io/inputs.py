"""Checks of user input made before any long work starts, shared by ``render``, ``demo`` and ``compare``.

Everything here raises :class:`CLIError` (one line, naming the problem and the
fix) and has no side effect: it reads the scene's XML (and its ``<include>``\\ s)
to find its integer parameters and the headers of the images it names, probes the
output folder with a temporary file that it removes at once, and writes nothing else.

- :class:`Limits`: the caps on what a model and a render may allocate (image
  pixels, bytes read, vertices, render pixels), overridable with
  ``--limit NAME=N`` (:func:`parse_limits`);
- :func:`check_spp`, :func:`check_seed`, :func:`check_int32`: sample counts,
  seeds and 32-bit integers from any source (``--spp``, ``-D``, the scene's own
  sampler or ``<integer>`` values);
- :func:`check_output`: the output name is not a folder, and its folder is (or
  can be created) writable;
- :func:`not_regular` and :func:`check_regular_file`: a file that is read must be a
  regular file (checked with ``os.stat``, before anything opens it: reading a FIFO or a
  device may block for ever);
- :func:`check_scene_before_render`: the loaded scene's sample count, film size
  and variant;
- :class:`Terminated` and :func:`raise_on_sigterm`: SIGTERM as an exception, so
  that temporary files are removed on the way out.
"""

from __future__ import annotations

import dataclasses
import errno
import math
import os
import re
import signal
import stat
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from mfnormal.io.image_headers import file_image_size
from mfnormal.io.scene_xml import PARAMETER, substitute

__all__ = ["CLIError", "Limits", "DEFAULT_LIMITS", "LIMIT_HELP", "parse_limits", "check_spp",
           "check_seed", "check_int32", "not_regular", "check_regular_file", "check_xml_scene",
           "check_output", "check_render_size",
           "check_scene_before_render", "Terminated", "raise_on_sigterm", "INT32_MAX", "UINT32_MAX"]

INT32_MIN, INT32_MAX = -(1 << 31), (1 << 31) - 1
UINT32_MAX = (1 << 32) - 1
#: The XML string properties that name a file: Mitsuba's ``filename`` and the plugin's maps.
FILE_STRINGS = ("filename", "normalmap", "heightmap")


class CLIError(Exception):
    """An error to report as one line, without a traceback."""


class Terminated(BaseException):
    """SIGTERM, raised where Python runs next (like KeyboardInterrupt for SIGINT)."""


def raise_on_sigterm() -> None:
    """Turn SIGTERM into :class:`Terminated` in this (main) thread."""
    def handler(signum, frame):
        raise Terminated()

    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, handler)


# -- Limits ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Limits:
    """What a model or a render may allocate; ``--limit NAME=N`` overrides each.

    - ``image_pixels``: width × height of one image of a glTF model or an XML scene
      (read from its header before it is decoded); 8192² by default.
    - ``texture_pixels``: the sum over all images of a glTF model or an XML scene;
      four 8192² maps.
    - ``data_bytes``: bytes read for one model: the .gltf/.glb file, its buffers
      (each at most its declared ``byteLength``) and image files; 2 GiB.
    - ``vertices``: vertices of a glTF scene after instancing (a mesh used by n
      nodes counts n times; flat-shaded and split vertices included); 2^24.
    - ``render_pixels``: width × height of a render; 2^25 (8K UHD is 2^24.98).
    """
    image_pixels: int = 1 << 26
    texture_pixels: int = 1 << 28
    data_bytes: int = 1 << 31
    vertices: int = 1 << 24
    render_pixels: int = 1 << 25

    def hint(self, name: str) -> str:
        return f"the limit is {getattr(self, name)}; raise it with --limit {name}=N"


DEFAULT_LIMITS = Limits()
LIMIT_NAMES = tuple(f.name for f in dataclasses.fields(Limits))
LIMIT_HELP = ("raise or lower a safety limit, NAME=N (repeatable); NAME is one of "
              + ", ".join(f"{n} (default {getattr(DEFAULT_LIMITS, n)})" for n in LIMIT_NAMES))


def parse_limits(items) -> Limits:
    """:class:`Limits` from ``--limit NAME=N`` strings (N a positive integer; ``2**30`` and
    ``1e9`` are accepted)."""
    changes = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in LIMIT_NAMES:
            raise CLIError(f"--limit expects NAME=N with NAME one of {', '.join(LIMIT_NAMES)}, got '{item}'")
        n = _positive_int(value.strip())
        if n is None:
            raise CLIError(f"--limit {name}={value}: expected a positive integer")
        changes[name] = n
    return dataclasses.replace(DEFAULT_LIMITS, **changes)


def _positive_int(text: str):
    m = re.fullmatch(r"(\d+)\s*\*\*\s*(\d+)", text)
    try:
        if m:
            if int(m.group(2)) > 64:
                return None
            n = int(m.group(1)) ** int(m.group(2))
        elif re.fullmatch(r"\d+", text):
            n = int(text)
        else:
            f = float(text)
            if not math.isfinite(f) or f != int(f):
                return None
            n = int(f)
    except (ValueError, OverflowError):
        return None
    return n if 1 <= n <= 1 << 62 else None


# -- Numbers -------------------------------------------------------------------------------------

def check_spp(spp, source: str) -> int:
    """A sample count from ``source`` (e.g. '--spp', "the scene's sampler"): 1 … 2^31 − 1."""
    if isinstance(spp, bool) or not isinstance(spp, int):
        raise CLIError(f"{source}: the sample count must be an integer, got {spp!r}")
    if spp < 1:
        raise CLIError(f"{source}: the sample count is {spp}; it must be at least 1")
    if spp > INT32_MAX:
        raise CLIError(f"{source}: the sample count {spp} is too large (at most {INT32_MAX})")
    return spp


def check_seed(seed, source: str = "--seed") -> int:
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= UINT32_MAX:
        raise CLIError(f"{source} must be an integer from 0 to {UINT32_MAX}, got {seed}")
    return seed


def check_int32(value: int, what: str, lo: int = INT32_MIN, hi: int = INT32_MAX) -> int:
    if not lo <= value <= hi:
        raise CLIError(f"{what}: {value} is out of range (it must be from {lo} to {hi})")
    return value


# -- Files -----------------------------------------------------------------------------------------

#: What a file that is not a regular file is, by its ``os.stat`` mode.
_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))
#: The errors of ``os.stat`` that mean "no such file" (as for ``Path.is_file``).
_MISSING = (errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP)


def not_regular(mode: int) -> str | None:
    """What a file of ``os.stat`` mode ``mode`` is ('a FIFO (named pipe)', 'a folder', ...),
    or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    return next((kind for test, kind in _KINDS if test(mode)), "not a regular file")


def check_regular_file(path, what: str, missing: str | None = None) -> None:
    """:class:`CLIError` when ``path`` (links followed) is a FIFO, a device, a folder or a
    socket: ``what`` names it in the message. Checked with ``os.stat``, so nothing is opened
    (opening a FIFO blocks until a writer comes). A missing file is ``missing``'s error when
    given (another error of the system, e.g. a name too long, is raised as it is), else left
    to the loader's own."""
    try:
        kind = not_regular(os.stat(path).st_mode)
    except (OSError, ValueError) as exc:   # missing, a loop of links, a NUL in the name, ...
        if not missing:
            return
        if isinstance(exc, ValueError) or exc.errno in _MISSING:
            raise CLIError(missing) from None
        raise
    if kind:
        raise CLIError(f"{what} is {kind}, not a regular file; give the path of a regular file")


def _named_file(el: ET.Element) -> tuple | None:
    """(file name as written, how the message names it) of an XML element that names
    a file: ``<include filename>``, any ``filename`` attribute, ``<string name="filename">``
    and the plugin's ``<string name="normalmap|heightmap">``; None for other elements."""
    if "filename" in el.attrib:
        return el.get("filename"), f"<{el.tag} filename>"
    if el.tag == "string" and el.get("name") in FILE_STRINGS and el.get("value") is not None:
        return el.get("value"), f'<string name="{el.get("name")}">'
    return None


def _check_named_file(el: ET.Element, file: Path, values: dict) -> None:
    """The file ``el`` names (relative to ``file``'s folder, as Mitsuba resolves it, else
    to the working folder) is not a FIFO, device or folder."""
    named = _named_file(el)
    if named is None:
        return
    name = substitute(named[0], values)
    path = file.parent / name
    if not os.path.exists(path):
        path = Path(name)
    check_regular_file(path, f"{file.name}: {named[1]} '{name}'")


def check_xml_scene(path, params: dict, limits: Limits = DEFAULT_LIMITS) -> None:
    """Two checks of the XML scene ``path`` and its ``<include>``\\ s, after substituting
    their ``<default>``\\ s and ``params`` (``-D``), before Mitsuba loads it:

    - every ``<integer>`` value is a 32-bit integer: Mitsuba stores integer properties in
      64 bits, but most plugins (samplers, integrators, this package's BSDF) use 32 bits,
      and a larger value fails deep inside a kernel;
    - every image a ``<texture>`` or ``<emitter>`` names (``filename``), or a ``<bsdf>`` as its
      map (``<string name="normalmap">``, ``heightmap``), declares at most
      ``limits.image_pixels`` pixels in its header, and all of them together at most
      ``limits.texture_pixels``, as for a glTF model (:mod:`mfnormal.io.image_headers`).
    - every file it names (``<include>``, ``filename``, the plugin's ``normalmap`` and
      ``heightmap`` strings) is a regular file (:func:`check_regular_file`), before
      anything opens it;
    - every mesh file a ``<shape type="ply">`` or ``"obj"`` names passes
      :func:`mfnormal.io.mesh_files.check_mesh_file` (face indices in range, finite numbers:
      Mitsuba's PLY loader crashes on a face index past the vertices).

    Files that do not parse, and images that are missing or of another format, are left
    to Mitsuba's own error."""
    seen, pixels = set(), 0

    def visit(file: Path, depth: int, values: dict):
        nonlocal pixels
        key = str(file.resolve()) if file.exists() else str(file)
        if depth > 16 or key in seen:
            return
        seen.add(key)
        try:
            root = ET.parse(file).getroot()
        except (ET.ParseError, OSError, ValueError):
            return
        values = {**{d.get("name"): d.get("value") for d in root.iter("default")}, **values}
        for el in root.iter():
            _check_named_file(el, file, values)
            if el.tag == "integer" and el.get("value") is not None:
                _check_xml_integer(el, file, values, params)
            elif el.tag == "include" and el.get("filename"):
                visit(file.parent / substitute(el.get("filename"), values), depth + 1, values)
            elif el.tag in ("texture", "emitter", "bsdf"):
                for prop in el.findall("string"):
                    named = substitute(prop.get("name", ""), values) in _IMAGE_NAMES[el.tag]
                    if named and prop.get("value") is not None:
                        image = file.parent / substitute(prop.get("value"), values)
                        pixels += _check_xml_image(image, file, limits, pixels)
        for shape in root.iter("shape"):        # after the loop: every file is a regular one
            _check_xml_mesh(shape, file, values)

    visit(Path(path), 0, dict(params))


def _check_xml_mesh(shape: ET.Element, file: Path, values: dict) -> None:
    """The mesh file of a ``<shape type="ply">`` or ``"obj"`` (as :func:`_check_named_file`
    finds it), checked before Mitsuba reads it."""
    from mfnormal.io.mesh_files import check_mesh_file

    kind = substitute(shape.get("type", ""), values)
    named = next((s for s in shape.findall("string") if s.get("name") == "filename"), None)
    if kind not in ("ply", "obj") or named is None or named.get("value") is None:
        return
    name = substitute(named.get("value"), values)
    path = file.parent / name
    if not os.path.exists(path):
        path = Path(name)
    if os.path.isfile(path):
        check_mesh_file(path, f'{file.name}: <shape type="{kind}"> \'{name}\'', CLIError)


#: The ``<string>`` properties that name an image file, by element: a texture's or an emitter's
#: ``filename``, and a BSDF's map given as a file name (``normalmap_microfacet``'s ``normalmap``
#: and ``heightmap``).
_IMAGE_NAMES = {"texture": ("filename",), "emitter": ("filename",), "bsdf": ("normalmap", "heightmap")}


def _check_xml_integer(el: ET.Element, file: Path, values: dict, params: dict) -> None:
    raw = el.get("value")
    text = substitute(raw, values).strip()
    if not re.fullmatch(r"[+-]?\d+", text):
        return
    value = int(text)
    if INT32_MIN <= value <= INT32_MAX:
        return
    names = PARAMETER.findall(raw)
    source = next((f"-D {n}={params[n]}" for n in names if n in params), None)
    where = f'<integer name="{el.get("name")}"> in {file.name}'
    raise CLIError(f"{source + ': ' if source else ''}{where} is {value}, outside the "
                   f"32-bit range ({INT32_MIN} to {INT32_MAX})")


def _check_xml_image(image: Path, file: Path, limits: Limits, so_far: int) -> int:
    """The pixel count that ``image`` declares (0 when it cannot be read), checked."""
    try:
        size = file_image_size(image) if image.is_file() else None
    except OSError:
        size = None
    if size is None:
        return 0
    fmt, w, h = size
    if w * h > limits.image_pixels:
        raise CLIError(f"{file.name}: the image {image.name} is {w}x{h} pixels ({fmt.upper()} header), "
                       f"more than an image may have ({limits.hint('image_pixels')})")
    if so_far + w * h > limits.texture_pixels:
        raise CLIError(f"{file.name}: the image {image.name} takes the scene's textures past "
                       f"{limits.texture_pixels} pixels ({limits.hint('texture_pixels')})")
    return w * h


# -- Output --------------------------------------------------------------------------------------

def check_output(output, flag: str = "-o") -> tuple[Path, Path]:
    """The (EXR, PNG) paths of ``output`` after checking that it is a file name (not a
    folder) and that its folder exists and is writable, or can be created."""
    try:
        return _check_output(output, flag)
    except OSError as exc:       # e.g. a name too long to stat, a loop of symbolic links
        raise CLIError(f"{flag} {output}: {exc.strerror or type(exc).__name__}; choose another "
                       "output name") from None


def _check_output(output, flag):
    from mfnormal.io.images import output_paths

    text = str(output)
    if not text.strip():
        raise CLIError(f"{flag}: the output name is empty")
    if max((len(os.fsencode(part)) for part in Path(text).parts), default=0) + 16 > 255:
        raise CLIError(f"{flag} {text}: a file or folder name is too long (at most 239 bytes; "
                       "the temporary files add 16)")
    if text.endswith(("/", os.sep)) or Path(text).is_dir():
        raise CLIError(f"{flag} {text} names a folder; give a file name without extension, "
                       f"e.g. {os.path.join(text.rstrip('/' + os.sep) or '.', 'render')}")
    exr, png = output_paths(output)
    for p in (exr, png):
        if p.is_dir():
            raise CLIError(f"{flag} {text}: {p} is a folder; choose another output name")
    existing = exr.parent
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise CLIError(f"{flag} {text}: {existing} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".mfnormal-probe.", dir=existing)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise CLIError(f"{flag} {text}: cannot write in {existing} ({reason}); choose a writable "
                       "folder") from None
    return exr, png


# -- The scene -------------------------------------------------------------------------------------

def check_render_size(width: int, height: int, limits: Limits, source: str) -> None:
    if width < 1 or height < 1:
        raise CLIError(f"{source}: the image is {width}x{height} pixels; both sides must be at least 1")
    if width * height > limits.render_pixels:
        raise CLIError(f"{source}: a {width}x{height} image has {width * height} pixels, more than "
                       f"a render may have ({limits.hint('render_pixels')})")


def check_scene_before_render(mi, scene, spp, limits: Limits, source: str) -> int:
    """The sample count a render of ``scene`` will use (``spp``, else the scene's own),
    after checking it, the film size and the variant; raises :class:`CLIError`."""
    sensors = scene.sensors()
    if not sensors:
        raise CLIError(f"{source} has no sensor (camera) to render from")
    sensor = sensors[0]
    if spp is None:
        spp = check_spp(int(sensor.sampler().sample_count()), f"{source}: the scene's sampler "
                                                               "(sample_count, or -D spp=N)")
    width, height = (int(v) for v in sensor.film().crop_size())
    check_render_size(width, height, limits, f"{source}: the film")
    if "polarized" in mi.variant():
        from mfnormal.io.scene_checks import normal_mapped_shapes
        if normal_mapped_shapes(scene):
            raise CLIError(f"variant {mi.variant()}: normalmap_microfacet does not support polarized "
                           "variants; use an rgb, mono or spectral one (e.g. llvm_ad_rgb)")
    return spp
