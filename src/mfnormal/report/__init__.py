"""``mfnormal compare``: every method of the catalogue (:mod:`mfnormal.methods`) rendered, the metrics,
and the self-contained HTML report."""
