"""Sources of the facet normal ω_p, and the frame the models see them in.

The models work on a :class:`~mfnormal.surface.shading.ShadingPoint`: a facet normal ω_p in a
base frame whose +z is the microsurface's macro normal ω_g. A source gives ω_p at a hit:

- :class:`~mfnormal.normals.normal_map.NormalMap`: a tangent-space normal map (``normalmap``);
- :class:`~mfnormal.normals.height_map.HeightMap`: a height map's gradient (``heightmap``);
- :class:`Flat`: no map, the shading normal itself (with ``macro_normal="geometric"``: the
  smooth-shaded mesh's microsurface, the shadow-terminator case);

each in the base shading frame ``si.sh_frame`` or in the mesh's vertex tangent frame
(:mod:`mfnormal.normals.tangents`). The macro normal (:mod:`mfnormal.normals.macro`) turns
them into the models' base frame: the shading normal (default) or the true triangle.
Every source (built from the plugin's parameters by
:func:`mfnormal.normals.source.from_properties`) offers :class:`mfnormal.normals.source.NormalSource`:
``facet_normal(si, active, nudge)``, ``slopes(attached)``, ``walls(attached)`` and
``local(width, attached)`` (the map's principal rms slopes, its walls and local
statistics, for the faithful model), ``flat_texels()``,
``parameters_changed(keys)`` and ``describe()``; none of them knows the plugin that owns it.
"""
