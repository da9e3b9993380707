"""The benchmarks, run as modules from the repository's root: ``python -m benchmarks.run --quick``
(docs/performance.md). Not installed with the package."""
