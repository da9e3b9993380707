"""The two-facet microsurface at a shading point: the layer the models and the normal sources share.

- :mod:`~mfnormal.surface.microsurface`: the two-facet microsurface (ω_t, projected areas, Λ,
  G1, the sawtooth height map), pure functions named as in the paper;
- :mod:`~mfnormal.surface.shading`: a shading point seen as that microsurface, with the nested
  BSDF on its facets.
"""
