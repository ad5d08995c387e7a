"""A Griffe extension for the API reference (mkdocs.yml loads it): the project's docstrings
are prose, written to read well in the source; this makes two of their conventions read well
on the site too, without changing what they say.

1. Lists of terms. A run of two or more lines that each open with `term:` followed by
   spaces, e.g. RenderConfig's

       algorithm:   which techniques of the one core are enabled (`TECHNIQUES`).
       max_depth:   maximum number of path segments ...
                    (continuation lines indented under the text)

   becomes a Markdown list (`- `algorithm`: ...`); the continuation lines stay where they
   are (Markdown joins them to their item). Terms are identifiers, a few of them
   (`a, b:`) or a label with a quoted name (`kind "merge":`).
2. Field comments. A dataclass or `eqx.Module` field documented by a trailing comment,

       nonfinite: Int[Array, ""]  # pixel-technique contributions that were NaN/Inf
       merge_imprecise: Array  # the hash grid could not resolve ...
       # ... (comment lines that follow, indented under it, continue it)

   gets the comment as its docstring, so the field is listed with it.
"""

from __future__ import annotations

import re

import griffe

_TERM = re.compile(r'^(?P<term>[A-Za-z_][\w.]*(?:, ?[A-Za-z_][\w.]*)*(?: "[^"]+")?):'
                   r'(?P<gap>\s+)(?P<text>\S.*)$')
_IDENT = re.compile(r"^[A-Za-z_][\w.]*(?:, ?[A-Za-z_][\w.]*)*$")


def _term(term: str) -> str:
    if _IDENT.match(term):
        return ", ".join(f"`{t.strip()}`" for t in term.split(","))
    head, _, rest = term.partition(" ")  # a label with a quoted name: kind "merge"
    return f"{head} `{rest.strip(chr(34))}`"


def term_lists(text: str) -> str:
    """Runs of two or more `term:` lines (with their continuation lines) as Markdown lists."""
    lines = text.split("\n")
    out, i = [], 0
    in_code = False
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("    ") and (not out or out[-1] == ""):
            in_code = True  # an indented code block (e.g. a formula): leave it alone
        elif ln and not ln.startswith(" "):
            in_code = False
        m = None if in_code else _TERM.match(ln)
        if m is None:
            out.append(ln)
            i += 1
            continue
        # the run: item lines and the non-blank lines between them
        j, run_items = i, []
        while j < len(lines) and lines[j].strip():
            if _TERM.match(lines[j]):
                run_items.append(j)
            j += 1
        if len(run_items) < 2:
            out.append(ln)
            i += 1
            continue
        if out and out[-1].strip():
            out.append("")
        for k in range(i, j):
            mk = _TERM.match(lines[k]) if k in run_items else None
            if mk:
                out.append(f"- {_term(mk['term'])}: {mk['text']}")
            else:
                out.append("  " + lines[k].strip())
        i = j
    return "\n".join(out)


def field_comment(lines: list[str], lineno: int) -> str | None:
    """The trailing comment of source line `lineno` (1-based) and the comment-only lines
    that continue it (indented past the field, or at its indentation while the sentence is
    unfinished), as one paragraph."""
    src = lines[lineno - 1]
    pos = _comment_start(src)
    if pos is None:
        return None
    indent = len(src) - len(src.lstrip())
    parts = [src[pos + 1:].strip()]
    for nxt in lines[lineno:]:
        stripped = nxt.strip()
        if not stripped.startswith("#") or stripped.startswith("# --"):
            break
        at = len(nxt) - len(nxt.lstrip())
        unfinished = not parts[-1].endswith((".", "!", "?", ")", ":"))
        if at < indent or (at == indent and not unfinished):
            break
        parts.append(stripped[1:].strip())
    text = " ".join(p for p in parts if p)
    return text or None


def _comment_start(src: str) -> int | None:
    """Index of the `#` that opens a trailing comment (outside string literals)."""
    quote = None
    for k, ch in enumerate(src):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            return k if src[:k].strip() else None
    return None


class ProseDocstrings(griffe.Extension):
    def on_object(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.is_alias:
            return
        if obj.is_attribute and obj.docstring is None and obj.parent is not None \
                and obj.parent.is_class and obj.lineno:
            try:
                lines = obj.lines_collection[obj.filepath]
            except (KeyError, TypeError):
                lines = None
            if lines:
                doc = field_comment(list(lines), obj.lineno)
                if doc:
                    obj.docstring = griffe.Docstring(doc, parent=obj)
        if obj.docstring is not None:
            obj.docstring.value = term_lists(obj.docstring.value)
