"""fits/literature_pure_water (see NOTES.md or the scripts' docstrings)."""
