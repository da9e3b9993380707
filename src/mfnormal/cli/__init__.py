"""The ``mfnormal`` command line (:mod:`mfnormal.cli.commands`): ``render``, ``demo`` and
``compare``, locally or on a Dask cluster (:mod:`mfnormal.render.cluster`)."""
