"""fits/caustic_robustness (see NOTES.md or the scripts' docstrings)."""
