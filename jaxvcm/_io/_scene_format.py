"""Writes the scene-format reference page from the schema (`_schema.format_markdown`):

    python -m jaxvcm._io._scene_format docs/scene-format.md

(no argument: the page on standard output).
"""

from __future__ import annotations

import sys

from ._schema import format_markdown, write_markdown

if __name__ == "__main__":
    if len(sys.argv) > 1:
        write_markdown(sys.argv[1])
    else:
        sys.stdout.write(format_markdown())
