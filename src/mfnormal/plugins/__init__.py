"""The Mitsuba plugins: the ``normalmap_microfacet`` BSDF and the ``mfnormal_path`` and ``mfnormal_prb``
integrators, registered by :func:`mfnormal.register`; their docstrings are the plugin reference."""
