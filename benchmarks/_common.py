"""Helpers shared by the benchmark modes: progress log, machine description, report files
(atomic text / JSON writes, in-place upsert of a `<!-- bench:TAG:begin/end -->` section)."""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import sys
from pathlib import Path

import jax
import numpy as np

import jaxvcm
from jaxvcm import __version__


class Log:
    def __init__(self, quiet: bool):
        self.quiet = quiet

    def __call__(self, msg: str) -> None:
        if not self.quiet:
            print(f"bench: {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- machine
def now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def machine() -> dict:
    try:
        devices = [str(d) for d in jax.devices()]
    except RuntimeError as e:  # pragma: no cover
        devices = [f"unavailable ({e})"]
    return {"date": now(), "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(), "jax": jax.__version__,
            "devices": devices, "jaxvcm": __version__}


def machine_line(m: dict) -> str:
    return (f"{m['date']}; os.cpu_count() = {m['cpu_count']}; {m['platform']} "
            f"({m['processor']}); Python {m['python']}; jax {m['jax']}; devices: "
            f"{', '.join(m['devices'])}; jaxvcm {m['jaxvcm']}")


# ----------------------------------------------------------------------------- files
def read_text(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""


def write_text(path: Path, text: str) -> None:
    with jaxvcm.atomic_path(str(path)) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def write_json(path: Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=1, default=json_default) + "\n")


def upsert_section(path: Path, tag: str, body: str) -> None:
    """Replace the `tag` section of the markdown file in place, or append it at the end;
    the rest of the file is left byte for byte as it was."""
    old = read_text(path)
    block = f"<!-- bench:{tag}:begin -->\n{body.rstrip()}\n<!-- bench:{tag}:end -->\n"
    pat = re.compile(rf"<!-- bench:{re.escape(tag)}:begin -->\n.*?"
                     rf"<!-- bench:{re.escape(tag)}:end -->\n?", re.S)
    if pat.search(old):
        new = pat.sub(lambda m: block, old, count=1)
    else:
        new = old + ("" if old.endswith("\n") or not old else "\n") + ("\n" if old else "") + block
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, new)


def publish(out: Path, tag: str, res: dict, body: str, log) -> None:
    """A mode's report: its markdown section of `out` (replaced in place or appended), the
    JSON sidecar `<out stem>_<tag>.json`, the section on stdout."""
    upsert_section(out, tag, body)
    write_json(out.with_name(f"{out.stem}_{tag}.json"), res)
    print(body)
    log(f"report -> {out}")


def section_head(title: str, res: dict) -> list[str]:
    """A mode's section header: title, the machine line and the command."""
    return [f"## {title}", "", f"- {machine_line(res['machine'])}",
            f"- command: `{res['command']}`"]
