"""Developer scripts that are Python, run as modules from the repository's root
(``python -m scripts.bit_identity``, docs/development.md). Not installed with the package."""
