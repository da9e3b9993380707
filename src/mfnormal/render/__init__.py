"""Rendering a scene, here or on a cluster: what the command line and the report both use.

- :mod:`~mfnormal.render.passes`: a render in passes on this machine, one accumulator for
  every schedule, and Mitsuba's setup (variant, plugins, threads);
- :mod:`~mfnormal.render.bundle`: a scene as it travels to a cluster's workers, with the
  files it names;
- :mod:`~mfnormal.render.tasks`: what a worker runs (its variant, its scenes, its chunks);
- :mod:`~mfnormal.render.cluster`: ``--cluster`` and the client that submits the tasks;
- :mod:`~mfnormal.render.worker`: the preload of a worker started by hand
  (``dask worker ADDRESS --preload mfnormal.render.worker``).
"""
