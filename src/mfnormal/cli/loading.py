"""The scene a command names, loaded: ``-D`` values, a glTF file's options, the checks.

:func:`load_scene` loads a Mitsuba XML scene (``-D key=value`` sets its ``$key`` defaults) or a
glTF 2.0 file (``-D`` gives :func:`mfnormal.io.gltf.load_gltf` its options, :data:`GLTF_OPTIONS`),
after the checks of :mod:`mfnormal.io.inputs` and before those of
:mod:`mfnormal.io.scene_checks`; every error is a :class:`~mfnormal.io.inputs.CLIError`.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mitsuba as mi

from mfnormal.io.inputs import CLIError, DEFAULT_LIMITS, Limits, check_int32, check_regular_file, check_xml_scene
from mfnormal.io.messages import one_line

__all__ = ["GLTF_OPTIONS", "parse_defines", "gltf_options", "load_scene"]


def parse_defines(defines: list[str]) -> dict[str, str]:
    params = {}
    for item in defines or []:
        if "=" not in item:
            raise CLIError(f"-D expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        key = key.strip()
        if not key.isidentifier():
            raise CLIError(f"-D {item}: '{key}' is not a parameter name (letters, digits and _)")
        params[key] = value
    return params


def _flag(text: str) -> bool:
    if text.strip().lower() in ("1", "true", "yes", "on"):
        return True
    if text.strip().lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"expected true or false, got '{text}'")


# -- D options of a glTF file: load_gltf's keyword arguments, parsed from text, with their ranges.
GLTF_OPTIONS = {"width": int, "height": int, "spp": int, "max_depth": int, "model": str,
                "tangents": str, "normal_maps": _flag, "lights": _flag, "macro_normal": str}
_GLTF_RANGES = {"width": (1, None), "height": (1, None), "spp": (1, None), "max_depth": (-1, None)}


def gltf_options(params: dict[str, str]) -> dict:
    """``-D`` values as :func:`mfnormal.io.gltf.load_gltf` keyword arguments, checked."""
    options = {}
    for key, value in params.items():
        if key not in GLTF_OPTIONS:
            raise CLIError(f"unknown -D option '{key}' for a glTF scene; use one of "
                           f"{', '.join(GLTF_OPTIONS)}")
        try:
            options[key] = GLTF_OPTIONS[key](value.strip() if GLTF_OPTIONS[key] is int else value)
        except ValueError:
            raise CLIError(f"-D {key}={value}: not a valid {key}") from None
        if key in _GLTF_RANGES:
            lo, _ = _GLTF_RANGES[key]
            check_int32(options[key], f"-D {key}={value}", lo=lo)
    return options


def _gltf_scene(mi, path: Path, params: dict[str, str], limits: Limits):
    """The scene dict of a glTF file, with -D key=value as load_gltf options."""
    from mfnormal.io.gltf import load_gltf

    options = gltf_options(params)
    return mi.load_dict(load_gltf(path, limits=limits, **options))


def load_scene(mi: ModuleType, path: str | os.PathLike, params: dict[str, str],
               limits: Limits = DEFAULT_LIMITS) -> mi.Scene:
    """A Mitsuba XML scene (``-D`` sets its ``$key`` defaults) or a glTF 2.0 file (``.gltf``, ``.glb``)."""
    from mfnormal.io.gltf import GLTF_SUFFIXES, GLTFError

    path = Path(path)
    check_regular_file(path, f"the scene {path}", f"scene file not found: {path}")
    gltf = path.suffix.lower() in GLTF_SUFFIXES
    if not gltf:
        check_xml_scene(path, params, limits)
    try:
        if gltf:
            scene = _gltf_scene(mi, path, params, limits)
        else:
            scene = mi.load_file(str(path), **params)
    except CLIError:
        raise
    except GLTFError as exc:
        raise CLIError(f"{path.name}: {exc}") from None
    except Exception as exc:
        raise CLIError(f"cannot load {path}: {one_line(exc)}") from None
    from mfnormal.io.scene_checks import check_scene
    check_scene(scene, CLIError, str(path))
    return scene
