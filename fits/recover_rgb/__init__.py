"""fits/recover_rgb (see NOTES.md or the scripts' docstrings)."""
