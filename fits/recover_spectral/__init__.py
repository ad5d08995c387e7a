"""fits/recover_spectral (see NOTES.md or the scripts' docstrings)."""
