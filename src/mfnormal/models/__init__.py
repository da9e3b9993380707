"""The paper's models, one module per idea, on the microsurface of :mod:`mfnormal.surface`.

- :mod:`~mfnormal.models.analytic`: the paper's analytic model;
- :mod:`~mfnormal.models.walk`: the separable and non-separable random walks;
- :mod:`~mfnormal.models.faithful`: the default model, the texel as the true geometry shows it;
- :mod:`~mfnormal.models.rng`: the random-number layout of the stochastic models;
- :mod:`~mfnormal.models.interface`: the one interface through which the plugin calls them.
"""
