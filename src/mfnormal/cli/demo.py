"""The bundled demo scene (a): a normal-mapped gold sphere and tiled ground plane under a sky.

The scene is described once, in ``scenes/demo.xml`` (:data:`mfnormal.scenes.assets.DEMO_XML`);
its textures are generated (:func:`mfnormal.scenes.assets.generate_demo_assets`): a strong
tangent-space normal map of pillowed tiles with a hemispherical rivet in each and a
small HDR sky with a sun. :func:`load_scene` loads that file with ``mi.load_file``;
:func:`demo_scene` converts the same file into a Python scene dict (for tests and
programmatic use, e.g. to swap the nested BSDF).

``model='classic'`` replaces the plugin by Mitsuba's built-in ``normalmap`` BSDF,
for comparison. The command line renders the demo: ``mfnormal demo`` (also
``mfnormal-demo``, see :mod:`mfnormal.cli`).
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import mitsuba as mi

from mfnormal.scenes.assets import DEMO_XML, generate_demo_assets
from mfnormal.methods import PLUGIN
from mfnormal.io.scene_xml import dicts_of_type, xml_to_dict

__all__ = ["CLASSIC", "scene_parameters", "demo_scene", "load_scene", "default_assets_dir"]

DEFAULT_SPP = 64
DEFAULT_RESOLUTION = (512, 384)
DEFAULT_MAX_DEPTH = 8

#: The value of ``model`` that selects Mitsuba's built-in normal mapping.
CLASSIC = "classic"


def default_assets_dir() -> Path:
    """Per-user cache directory for the generated textures (where :func:`demo_scene` and
    :func:`load_scene` write them unless told otherwise)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mfnormal" / "demo_assets"


def scene_parameters(model: str = "faithful", spp: int = DEFAULT_SPP,
                     resolution=DEFAULT_RESOLUTION, assets: dict | None = None,
                     strength: float = 1.0, max_depth: int = DEFAULT_MAX_DEPTH) -> dict:
    """The ``$name`` substitutions of :data:`mfnormal.scenes.assets.DEMO_XML`, as strings."""
    width, height = resolution
    params = {"spp": str(int(spp)), "width": str(int(width)), "height": str(int(height)),
              "max_depth": str(int(max_depth)), "model": str(model),
              "strength": repr(float(strength))}
    if assets is not None:
        params["normalmap"] = str(Path(assets["normalmap"]).resolve())
        params["envmap"] = str(Path(assets["envmap"]).resolve())
    return params


def demo_scene(model: str = "faithful", bsdf: dict | None = None, spp: int = DEFAULT_SPP,
               resolution=DEFAULT_RESOLUTION, assets_dir=None, strength: float = 1.0,
               max_depth: int = DEFAULT_MAX_DEPTH) -> dict:
    """The demo scene as a Mitsuba scene dict.

    Args:
        model: ``normalmap_microfacet``'s ``model`` parameter; ``'classic'``
            uses Mitsuba's built-in ``normalmap`` BSDF instead.
        bsdf: optional nested BSDF dict replacing the materials of both the
            sphere and the ground.
        spp, resolution, max_depth: samples per pixel, (width, height), path length.
        assets_dir: where the generated textures are written
            (default: :func:`default_assets_dir`).
        strength: normal map strength (ignored by ``'classic'``).

    The active variant must be set before calling this (``import mfnormal`` registers the
    plugins for it).
    """
    assets = generate_demo_assets(default_assets_dir() if assets_dir is None else assets_dir)
    classic = model == CLASSIC
    params = scene_parameters(model="analytic" if classic else model, spp=spp,
                              resolution=resolution, assets=assets, strength=strength,
                              max_depth=max_depth)
    scene = xml_to_dict(DEMO_XML, **params)
    for nm in list(dicts_of_type(scene, PLUGIN)):
        if bsdf is not None:
            nm["bsdf"] = copy.deepcopy(bsdf)
        if classic:
            nm["type"] = "normalmap"
            for key in ("model", "strength", "normalmap_convention"):
                nm.pop(key, None)
    return scene


def load_scene(model: str = "faithful", spp: int = DEFAULT_SPP, resolution=DEFAULT_RESOLUTION,
               assets_dir=None, strength: float = 1.0,
               max_depth: int = DEFAULT_MAX_DEPTH) -> "mi.Scene":
    """Generate the textures and load the demo scene in the active variant.

    Loads :data:`mfnormal.scenes.assets.DEMO_XML` with ``mi.load_file``; ``model='classic'``
    goes through :func:`demo_scene` instead (the XML names the plugin).
    """
    if model == CLASSIC:
        return mi.load_dict(demo_scene(model=model, spp=spp, resolution=resolution,
                                       assets_dir=assets_dir, strength=strength,
                                       max_depth=max_depth))
    assets = generate_demo_assets(default_assets_dir() if assets_dir is None else assets_dir)
    params = scene_parameters(model=model, spp=spp, resolution=resolution,
                              assets=assets, strength=strength, max_depth=max_depth)
    return mi.load_file(str(DEMO_XML), **params)

