"""Fits and studies with jaxvcm; run them as modules from the repository root
(`python -m fits.jerlov_types.run`)."""
