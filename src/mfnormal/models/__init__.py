"""The paper's models, one module per idea.

- :mod:`~mfnormal.models.microsurface`: the two-facet microsurface (ω_t, projected areas, Λ,
  G1, the sawtooth height map), pure functions named as in the paper;
- :mod:`~mfnormal.models.shading`: a shading point seen as that microsurface, with the nested
  BSDF on its facets;
- :mod:`~mfnormal.models.analytic`: the paper's analytic model;
- :mod:`~mfnormal.models.walk`: the separable and non-separable random walks;
- :mod:`~mfnormal.models.faithful`: the default model, the texel as the true geometry shows it;
- :mod:`~mfnormal.models.rng`: the random-number layout of the stochastic models;
- :mod:`~mfnormal.models.interface`: the one interface through which the plugin calls them.
"""
