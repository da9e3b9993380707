"""Independent references for the tests and for ``python -m validation.run``.

Each one is written from the geometry of the microsurface, not from the model
code it checks (docs/model.md §7):

- ``sawtooth``: a numpy brute-force ray tracer of the periodic sawtooth cross-section;
- ``microgeometry``: Mitsuba's own ray tracer on a real triangle mesh of that sawtooth;
- ``sawtooth_compare``: exit-direction histograms of the models next to ``sawtooth``;
- ``naive_walk``: the non-separable evaluation with one sampled height and binary
  shadow tests, the estimator the supplemental's interval tracking improves on.

It imports nothing from the tests (they import it, as ``validation.reference``); ``arrays`` holds
the Dr.Jit inputs both build.
"""
