"""glTF materials as Mitsuba BSDF dicts: ``principled``, wrapped in ``normalmap_microfacet`` where mapped.

:class:`Materials` turns a material into a ``principled`` BSDF (base colour, metallic,
roughness, with their textures and factors) and, where it has a ``normalTexture`` (its
``scale`` is the plugin's ``strength``; a negative one flips the map's x and y), wraps it in
``normalmap_microfacet``, decoding the map in the mesh's vertex tangents where it has them.
Base colour is sRGB, normals and metallic-roughness are linear (roughness in G, metallic in
B). Texture coordinate sets other than ``TEXCOORD_0``, ``KHR_texture_transform``, emission,
alpha and material extensions are ignored, each with one warning.
"""

from __future__ import annotations

import numpy as np

from mfnormal.io.gltf_arrays import GLTFFile, warn
from mfnormal.io.meshes import TANGENT_ATTR

_WRAP = {33071: "clamp", 33648: "mirror", 10497: "repeat"}
_NEAREST = {9728, 9984, 9986}


def _srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _channels(arr, n):
    """The first ``n`` colour channels (grey repeated), alpha dropped."""
    colour = arr[:, :, :1].repeat(3, axis=2) if arr.shape[2] in (1, 2) else arr[:, :, :3]
    return np.ascontiguousarray(colour[:, :, :n])


class Materials:
    """glTF materials → Mitsuba BSDF dicts, textures decoded once."""

    def __init__(self, f: GLTFFile, model: str, tangents: str, normal_maps: bool, macro_normal: str = "shading"):
        self.f, self.model, self.tangents, self.normal_maps = f, model, tangents, normal_maps
        self.macro_normal = macro_normal
        self._warned = set()

    def warn_once(self, key, msg):
        if key not in self._warned:
            self._warned.add(key)
            warn(msg)

    def _texture(self, info, what):
        """(raw image array, sampler settings) of a textureInfo, or (None, None)."""
        if info is None:
            return None, None
        if (info.texCoord or 0) != 0:
            self.warn_once(("texcoord", what), f"{what} uses TEXCOORD_{info.texCoord}; "
                                               "only TEXCOORD_0 is supported, using it")
        if info.extensions and "KHR_texture_transform" in info.extensions:
            self.warn_once(("transform", what), f"KHR_texture_transform on {what} is ignored")
        tex = self.f.gltf.textures[info.index]
        if tex.source is None:
            self.warn_once(("source", info.index), f"texture {info.index} has no PNG/JPEG source "
                                                   "(a texture extension?); ignored")
            return None, None
        arr = self.f.image(tex.source)
        if arr is None:
            return None, None
        sampler = self.f.gltf.samplers[tex.sampler] if tex.sampler is not None else None
        settings = {"wrap_mode": _WRAP.get(getattr(sampler, "wrapS", None), "repeat"),
                    "filter_type": "nearest" if getattr(sampler, "magFilter", None) in _NEAREST
                    else "bilinear"}
        return arr, settings

    @staticmethod
    def _bitmap(data, settings):
        import mitsuba as mi

        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(data, dtype=np.float32)),
                "raw": True, **settings}

    def normal_texture(self, mat):
        """(bitmap dict, strength) of the material's normal map, or (None, None)."""
        if mat is None or mat.normalTexture is None or not self.normal_maps:
            return None, None
        arr, settings = self._texture(mat.normalTexture, "normalTexture")
        if arr is None:
            return None, None
        if arr.shape[2] < 3:
            self.warn_once(("nchan", id(mat)), "a normalTexture with fewer than 3 channels is ignored")
            return None, None
        scale = 1.0 if mat.normalTexture.scale is None else float(mat.normalTexture.scale)
        rgb = arr[:, :, :3]
        if scale < 0:
            # A negative scale flips the map's x and y: 2(1 − c) − 1 = −(2c − 1).
            rgb = rgb.copy()
            rgb[:, :, :2] = 1.0 - rgb[:, :, :2]
            scale = -scale
        return self._bitmap(rgb, settings), scale

    def principled(self, mat) -> dict:
        pbr = mat.pbrMetallicRoughness if mat is not None else None
        base = list((pbr.baseColorFactor if pbr and pbr.baseColorFactor else [1, 1, 1, 1])[:3])
        metallic = 1.0 if pbr is None or pbr.metallicFactor is None else float(pbr.metallicFactor)
        roughness = 1.0 if pbr is None or pbr.roughnessFactor is None else float(pbr.roughnessFactor)
        bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": base},
                "metallic": metallic, "roughness": roughness}
        if pbr is not None:
            arr, settings = self._texture(pbr.baseColorTexture, "baseColorTexture")
            if arr is not None:
                colour = _srgb_to_linear(_channels(arr, 3)) * np.float32(base)
                bsdf["base_color"] = self._bitmap(colour, settings)
            arr, settings = self._texture(pbr.metallicRoughnessTexture, "metallicRoughnessTexture")
            if arr is not None:
                if arr.shape[2] < 3:
                    arr = _channels(arr, 3)
                bsdf["roughness"] = self._bitmap(arr[:, :, 1:2] * np.float32(roughness), settings)
                bsdf["metallic"] = self._bitmap(arr[:, :, 2:3] * np.float32(metallic), settings)
        if mat is not None:
            if mat.emissiveTexture is not None or any(mat.emissiveFactor or []):
                self.warn_once("emissive", "emission is ignored")
            if mat.alphaMode not in (None, "OPAQUE"):
                self.warn_once("alpha", f"alphaMode {mat.alphaMode} is rendered opaque")
            if mat.extensions:
                for ext in mat.extensions:
                    self.warn_once(ext, f"material extension {ext} is ignored")
        return bsdf

    def bsdf(self, index, has_uv: bool, has_tangents: bool, smooth: bool = False):
        """The Mitsuba BSDF dict of material ``index`` (None: the default material) on a mesh
        (``smooth``: smooth-shaded, which ``macro_normal="geometric"`` wraps even without a map)."""
        mat = self.f.gltf.materials[index] if index is not None else None
        bsdf = self.principled(mat)
        normalmap, strength = self.normal_texture(mat) if has_uv else (None, None)
        geometric = smooth and self.macro_normal == "geometric"
        if normalmap is not None:
            bsdf = {"type": "normalmap_microfacet", "normalmap": normalmap, "bsdf": bsdf,
                    "strength": strength, "model": self.model,
                    "tangents": TANGENT_ATTR if has_tangents else "mitsuba"}
            if geometric:
                bsdf["macro_normal"] = "geometric"
        elif geometric:
            bsdf = {"type": "normalmap_microfacet", "macro_normal": "geometric", "bsdf": bsdf, "model": self.model}
        if mat is not None and mat.doubleSided:
            bsdf = {"type": "twosided", "bsdf": bsdf}
        return bsdf

    def wants_tangents(self, index) -> bool:
        mat = self.f.gltf.materials[index] if index is not None else None
        return (self.tangents != "mitsuba" and self.normal_maps and mat is not None
                and mat.normalTexture is not None)
