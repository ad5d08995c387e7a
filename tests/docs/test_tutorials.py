"""The tutorials' code runs as printed (docs/tutorials/*.md).

Each page's ```python blocks run in order, in one namespace, from the repository root, in
a fresh Python process: the reader's JAX defaults (no float64, standard dtype promotion:
not the suite's conftest settings), matplotlib without a display. The pages assert what
they show (the algorithms agree within their standard errors, the fits recover the truth,
the gradient matches finite differences), so a page whose code or claims no longer hold
fails here. `python docs/tutorials/make_figures.py --check PAGE` is the same run by hand.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
PAGES = sorted(p.stem for p in (ROOT / "docs" / "tutorials").glob("*.md"))


def test_every_tutorial_has_code():
    assert PAGES == ["fit", "jax", "render"]
    for page in PAGES:
        text = (ROOT / "docs" / "tutorials" / f"{page}.md").read_text(encoding="utf-8")
        assert text.count("```python") >= 3, page
        assert "assert" in text, page


@pytest.mark.parametrize("page", PAGES)
def test_tutorial_runs(page):
    env = dict(os.environ)
    env["MPLBACKEND"] = "Agg"
    # the suite's persistent compilation cache (tests/conftest.py), shared with the page
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str(ROOT / ".jax_cache"))
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
    for name in ("JAX_ENABLE_X64", "JAX_NUMPY_DTYPE_PROMOTION"):
        env.pop(name, None)
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "tutorials" / "make_figures.py"),
                           "--check", page],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (
        f"docs/tutorials/{page}.md failed (exit {proc.returncode}):\n"
        f"{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")
