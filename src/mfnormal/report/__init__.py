"""``mfnormal compare``: the catalogue of normal-mapping methods, rendering each, the metrics,
and the self-contained HTML report."""
