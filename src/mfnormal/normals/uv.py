"""A map's texture coordinates: its uv transforms checked, its lookups made at finite uv.

A bitmap's ``to_uv`` that holds NaN or ±inf (``<scale x="inf"/>``) makes every uv non-finite,
and a non-finite uv makes Mitsuba 3.9.1's bitmap read outside its data: ``eval_1_grad``
crashes the process, ``eval_3`` returns whatever memory it reads, and inside the random walks'
symbolic loops such lookups have hung the render for good. So such a transform is refused where
the plugin gets it (:func:`check_uv_transforms`, at load and on ``mi.traverse`` updates), and
the plugin looks textures up at :func:`finite_uv` (a non-finite uv, e.g. a mesh's NaN texture
coordinate or a huge transform's overflow, as uv = 0; finite uvs unchanged, bit for bit).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.normals.strength import fail

__all__ = ["uv_transforms", "non_finite_uv_transforms", "check_uv_transforms", "finite_uv"]


def uv_transforms(params) -> dict:
    """``{key: 3×3 numpy matrix}`` of every ``to_uv`` among the traversed ``params`` (a texture's
    own, and those of the textures it nests)."""
    out = {}
    for key in params.keys():
        if key == "to_uv" or key.endswith(".to_uv"):
            out[key] = np.array(params[key].matrix, dtype=np.float64)
    return out


def non_finite_uv_transforms(transforms: dict) -> list:
    """The keys of :func:`uv_transforms`' matrices that hold NaN or ±inf."""
    return [key for key, m in transforms.items() if not np.all(np.isfinite(m))]


def check_uv_transforms(texture, name: str, restore: dict | None = None) -> dict:
    """The ``to_uv`` matrices of ``texture`` (the plugin's ``name``: 'normalmap', 'heightmap'),
    each finite, else ValueError (one line). ``restore``: the matrices checked before, written
    back into the texture before raising (a refused ``mi.traverse`` update leaves nothing changed)."""
    params = mi.traverse(texture)
    found = uv_transforms(params)
    for key in non_finite_uv_transforms(found):
        if restore:
            for k, old in restore.items():
                params[k] = mi.ScalarTransform3f(old.tolist())
            params.update()
        where = "to_uv" if key == "to_uv" else f"to_uv of its nested texture '{key[:-len('.to_uv')]}'"
        fail(f"the {name} texture's {where} holds NaN or infinity; give its <transform "
             "name=\"to_uv\"> (or 'to_uv') finite scale, translate and rotate values")
    return found


def finite_uv(si):
    """``si`` with its non-finite uv coordinates as 0 (a copy; ``si`` itself where it has no uv)."""
    if not hasattr(si, "uv"):
        return si
    out = mi.SurfaceInteraction3f(si)
    out.uv = dr.select(dr.isfinite(si.uv), si.uv, 0.0)
    return out
