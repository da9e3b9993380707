"""The bundled scenes (``demo``, ``model``, ``eggcrate``, ``water``, ``glass``: XML files beside this module) and
their procedurally generated assets (:mod:`mfnormal.scenes.assets`, :mod:`mfnormal.scenes.sky`)."""
