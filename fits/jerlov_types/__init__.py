"""fits/jerlov_types (see NOTES.md or the scripts' docstrings)."""
