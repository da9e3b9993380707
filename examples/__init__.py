"""Examples that use the validation harnesses, run as modules from the repository's root
(``python -m examples.inverse_rendering``). Not installed with the package."""
