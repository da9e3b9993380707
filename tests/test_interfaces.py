"""The declared interfaces: every model offers :class:`mfnormal.models.interface.Model`, every normal
source :class:`mfnormal.normals.source.NormalSource`, every macro frame
:class:`mfnormal.surface.shading.MacroFrame` (the null one for the shading frame), and a shading
point carries only the fields it declares."""

from __future__ import annotations

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import numpy as np
import pytest

from helpers import encode, make_bsdf, make_si, vec3
from variant import VARIANT

mi.set_variant(VARIANT)
mfnormal.register()

from mfnormal.models import interface  # noqa: E402
from mfnormal.normals.macro import Macro  # noqa: E402
from mfnormal.normals.source import NormalSource  # noqa: E402
from mfnormal.surface.shading import SHADING_FRAME, MacroFrame  # noqa: E402

DIFFUSE = {"type": "diffuse"}
TILTED = encode(np.array([[0.3, 0.1, 0.95]] * 4))


@pytest.mark.parametrize("name", interface.MODELS)
def test_every_registered_model_offers_the_interface(name):
    bsdf = make_bsdf(DIFFUSE, TILTED, model=name)
    assert isinstance(bsdf.model, interface.Model) and bsdf.model.name == name
    assert interface.REGISTRY[name] is type(bsdf.model)


def test_the_registry_decides_what_a_model_accepts():
    """A tangent facet of the nested material, a transmitting nested BSDF: each model's class says."""
    glass = mi.load_dict({"type": "dielectric"})
    assert [n for n, m in interface.REGISTRY.items() if "same" in m.tangent_facets] == ["separable", "nonseparable"]
    assert [n for n in interface.MODELS if interface.refusal(n, glass) is None] == ["faithful"]
    with pytest.raises(ValueError, match="tangent_facet 'same' needs model='separable' or 'nonseparable'; "
                                         "the analytic model"):
        interface.make("analytic", "same", mi.load_dict(DIFFUSE), None, (8, 3, 4.0))


def _plugin(**params):
    return mi.load_dict({"type": "normalmap_microfacet", "bsdf": DIFFUSE, **params})


HEIGHTS = {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(np.linspace(0, 1, 16, dtype=np.float32).reshape(4, 4))}


def test_every_normal_source_offers_the_interface():
    """A normal map, a height map, none (the geometric macro normal's flat source)."""
    sources = [make_bsdf(DIFFUSE, TILTED).source, _plugin(heightmap=HEIGHTS).source,
               _plugin(macro_normal="geometric").source]
    assert [type(s).__name__ for s in sources] == ["NormalMap", "HeightMap", "Flat"]
    assert all(isinstance(s, NormalSource) for s in sources)
    assert [s.local(8.0) is None for s in sources] == [False, True, True]


def test_a_shading_point_declares_its_fields_and_its_macro_frame():
    si = make_si(np.array([[0.0, 0.6, 0.8]]), 2)
    radiance, importance = mi.BSDFContext(), mi.BSDFContext(mi.TransportMode.Importance)
    # (the default sees a coarse mesh's rim on the triangle in radiance mode: a Macro, the identity
    # elsewhere; normals/macro.py turned_normal)
    for macro_normal, model, ctx, frame in (("shading", "analytic", radiance, SHADING_FRAME),
                                            ("shading", "faithful", importance, SHADING_FRAME),
                                            ("shading", "faithful", radiance, None),
                                            ("geometric", "faithful", radiance, None)):
        sp = make_bsdf(DIFFUSE, TILTED, model=model, macro_normal=macro_normal).shading_point(ctx, si)
        assert isinstance(sp.macro, MacroFrame)
        assert sp.macro is frame if frame is not None else isinstance(sp.macro, Macro)
        with pytest.raises(AttributeError):
            sp.undeclared = True
    w = vec3(np.array([[0.2, 0.3, 0.9]]))
    assert SHADING_FRAME.to_macro(w) is w and SHADING_FRAME.from_macro(w) is w
