"""The tutorials' code, run as the reader sees it, and their figures.

Every ```python block of a tutorial page runs, in order, in one namespace, from the
repository root. The pages draw their figures themselves: every matplotlib figure the
code leaves in a variable named `fig_NAME` is saved as docs/tutorials/PAGE_NAME.png.

    python docs/tutorials/make_figures.py              # all pages, at the figures' sizes
    python docs/tutorials/make_figures.py render jax   # some pages
    python docs/tutorials/make_figures.py --check fit  # the code as printed; writes nothing

The figures come from the same code at larger sizes: a page's settings are top-level lines
`NAME = number` (e.g. `SIZE = 32`), and `FIGURE_SETTINGS` replaces some of them. With
`--check` (what tests/docs/test_tutorials.py runs) the code runs exactly as printed.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
PAGES = ("render", "fit", "jax")

# the settings of each page's figures (the page prints its own, smaller ones)
FIGURE_SETTINGS = {
    "render": {"SIZE": 128, "PASSES": 256},
    "fit": {},
    "jax": {"SIZE": 96, "KEYS": 64},
}

_FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.S | re.M)


def code_blocks(page: str) -> list[tuple[int, str]]:
    """The ```python blocks of docs/tutorials/PAGE.md: (line of the block's first code
    line, code)."""
    with open(os.path.join(HERE, page + ".md"), encoding="utf-8") as f:
        text = f.read()
    return [(text.count("\n", 0, m.start(1)) + 1, m.group(1)) for m in _FENCE.finditer(text)]


def with_settings(code: str, settings: dict) -> str:
    """`code` with its top-level `NAME = number` lines set to `settings[NAME]`."""
    for name, value in settings.items():
        code = re.sub(rf"^{name} = [0-9.e+-]+", f"{name} = {value!r}", code, flags=re.M)
    return code


def run_page(page: str, settings: dict | None = None) -> dict:
    """Run the page's blocks in order in one namespace (from the repository root) and
    return it. A failing block raises with the page and line in its traceback."""
    ns = {"__name__": "__tutorial__"}
    for line, code in code_blocks(page):
        code = with_settings(code, settings or {})
        # compile with the page as the file name and the block's line offset, so a
        # traceback points at the page's own line
        compiled = compile("\n" * (line - 1) + code, os.path.join("docs", "tutorials",
                                                                   page + ".md"), "exec")
        t0 = time.perf_counter()
        exec(compiled, ns)
        print(f"{page}.md:{line}: block ran in {time.perf_counter() - t0:.1f} s", flush=True)
    return ns


def save_figures(page: str, ns: dict) -> list[str]:
    paths = []
    for name, value in ns.items():
        if name.startswith("fig_") and hasattr(value, "savefig"):
            path = os.path.join(HERE, f"{page}_{name[4:]}.png")
            value.savefig(path, dpi=110)
            paths.append(path)
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pages", nargs="*", metavar="PAGE",
                    help=f"some of {', '.join(PAGES)} (default: all)")
    ap.add_argument("--check", action="store_true",
                    help="run the code exactly as printed and write no figures")
    a = ap.parse_args(argv)
    for page in a.pages:
        if page not in PAGES:
            ap.error(f"unknown page {page!r}; one of {', '.join(PAGES)}")
    os.chdir(ROOT)
    import matplotlib

    matplotlib.use("Agg")
    for page in a.pages or PAGES:
        t0 = time.perf_counter()
        ns = run_page(page, None if a.check else FIGURE_SETTINGS[page])
        print(f"{page}.md: {time.perf_counter() - t0:.1f} s", flush=True)
        if not a.check:
            for path in save_figures(page, ns):
                print(os.path.relpath(path, ROOT))
    return 0


if __name__ == "__main__":
    sys.exit(main())
