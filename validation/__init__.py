"""The validation harnesses, run as modules from the repository's root (``python -m validation.run``,
docs/validation.md), and the independent references the tests share (:mod:`validation.reference`).
Not installed with the package."""
