"""The API reference (docs/api/*.md) documents exactly the public API: every name that
`jaxvcm/__init__.py` re-exports has a `::: jaxvcm.NAME` entry, and every entry names one of
them (mkdocstrings would fail the strict site build on a missing object; this says which
name, without building the site)."""

from __future__ import annotations

import pathlib
import re
import types

import jaxvcm

ROOT = pathlib.Path(__file__).resolve().parents[2]


def public_names() -> set[str]:
    return {n for n, v in vars(jaxvcm).items()
            if not n.startswith("_") and not isinstance(v, types.ModuleType)}


def documented() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for page in sorted((ROOT / "docs" / "api").glob("*.md")):
        for name in re.findall(r"^::: jaxvcm\.(\w+)\s*$", page.read_text(encoding="utf-8"),
                               re.M):
            out.setdefault(name, []).append(page.name)
    return out


def test_every_public_name_is_documented_once():
    docs = documented()
    missing = sorted(public_names() - set(docs))
    assert not missing, f"public names without an entry in docs/api/*.md: {missing}"
    twice = {n: p for n, p in docs.items() if len(p) > 1}
    assert not twice, f"documented more than once: {twice}"


def test_every_entry_is_public():
    extra = sorted(set(documented()) - public_names())
    assert not extra, f"docs/api/*.md entries that jaxvcm does not export: {extra}"
