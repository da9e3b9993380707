"""The normal-mapping methods the tools compare, in one catalogue.

A :class:`Method` is one way to put a tangent-space normal map on a nested BSDF:

- ``flat``: the nested BSDF alone (no normal map);
- ``classic`` / ``classic_fixed``: Mitsuba's built-in ``normalmap`` with its
  fixes (``flip_invalid_normals``, ``use_shadowing_function``) off / on;
- ``faithful``, ``analytic``, ``separable_*``, ``nonseparable_*``:
  ``normalmap_microfacet`` with each model and tangent facet.

:data:`METHODS` is what ``mfnormal compare`` renders; the benchmarks
(``benchmarks/run.py``) and the true-geometry harness
(:mod:`validation.heightfield`) name their methods after it and build their BSDFs
with :meth:`Method.bsdf`, :func:`classic_bsdf` and :func:`plugin_bsdf`. How an XML
scene is rewritten for a method is :func:`mfnormal.io.scene_xml.rewrite`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PLUGIN", "Method", "METHODS", "METHOD_BY_KEY", "classic_bsdf", "plugin_bsdf"]

PLUGIN = "normalmap_microfacet"
#: The models without a ``tangent_facet`` parameter (their tangent facet is a mirror).
MIRROR_ONLY = ("analytic", "faithful")


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    kind: str                       # 'flat', 'classic' or 'microfacet'
    model: str | None = None
    tangent_facet: str | None = None
    fixes: bool = False
    about: str = ""

    def plugin_params(self) -> dict:
        """``normalmap_microfacet``'s parameters for this method (``model``, and
        ``tangent_facet`` for the random walks)."""
        params = {"model": self.model}
        if self.model not in MIRROR_ONLY:
            params["tangent_facet"] = self.tangent_facet
        return params

    def bsdf(self, nested: dict, normalmap: dict) -> dict:
        """The scene dict of this method around ``nested`` with the texture dict ``normalmap``."""
        if self.kind == "flat":
            return nested
        if self.kind == "classic":
            return classic_bsdf(nested, normalmap, self.fixes)
        return plugin_bsdf(nested, normalmap, **self.plugin_params())


def classic_bsdf(nested: dict, normalmap: dict, fixes: bool) -> dict:
    """Mitsuba's ``normalmap`` around ``nested``, its two fixes on or off."""
    return {"type": "normalmap", "normalmap": normalmap, "bsdf": nested,
            "flip_invalid_normals": fixes, "use_shadowing_function": fixes}


def plugin_bsdf(nested: dict, normalmap: dict, **params) -> dict:
    """``normalmap_microfacet`` around ``nested`` with ``params`` (model, tangent_facet, ...)."""
    return {"type": PLUGIN, "normalmap": normalmap, "bsdf": nested, **params}


METHODS = (
    Method("flat", "flat", "flat", about="the nested BSDF alone, no normal map"),
    Method("classic", "normalmap", "classic", fixes=False,
           about="Mitsuba's normalmap, flip_invalid_normals and use_shadowing_function "
                 "off: classic normal mapping"),
    Method("classic_fixed", "normalmap + fixes", "classic", fixes=True,
           about="Mitsuba's normalmap with flip_invalid_normals and use_shadowing_function "
                 "on (its defaults)"),
    Method("faithful", "faithful (default)", "microfacet", "faithful", "specular",
           about="normalmap_microfacet, model=faithful (the default): the texel among neighbours "
                 "of the map's own rms slope, energy kept, light tracing sees its adjoint"),
    Method("analytic", "analytic", "microfacet", "analytic", "specular",
           about="normalmap_microfacet, model=analytic (≤ 2 facet bounces, mirror tangent facet)"),
    Method("separable_specular", "separable / specular", "microfacet", "separable", "specular",
           about="random walk, separable masking-shadowing, mirror tangent facet"),
    Method("separable_same", "separable / same", "microfacet", "separable", "same",
           about="random walk, separable masking-shadowing, nested material on the tangent facet"),
    Method("nonseparable_specular", "nonseparable / specular", "microfacet", "nonseparable",
           "specular", about="random walk, height-correlated masking-shadowing, mirror tangent facet"),
    Method("nonseparable_same", "nonseparable / same", "microfacet", "nonseparable", "same",
           about="random walk, height-correlated masking-shadowing, nested material on the "
                 "tangent facet"),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}
