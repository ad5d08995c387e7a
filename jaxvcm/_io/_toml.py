"""Reading a TOML file and validating its values, with one-line errors
'FILE: FIELD: problem' that name the offending field (`SceneError`, `_Ctx`).

Every number of a scene goes through `_Ctx.number`, the one place that turns TOML values
into floats: a value is rejected (one line naming the field) unless it is a finite number
inside the field's range (a `Range` of the schema, `_schema.py`).
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import tomllib
from typing import Any

import numpy as np

from ._schema import (ANY, CHANNELS, COORD, DIRECTION, MAX_FILE_BYTES, MAX_LENGTH, REL_SIZE,
                      SIZE, Range)

__all__ = ["ANY", "CHANNELS", "COORD", "DIRECTION", "MAX_LENGTH", "REL_SIZE", "SIZE", "Range",
           "SceneError", "key_path", "read_toml"]


class SceneError(ValueError):
    """A malformed scene file. str() is one line: 'FILE: FIELD: problem'."""


def _fmt(v) -> str:
    """A number for a message; a huge integer by its size (str() of one with more than
    4300 digits raises)."""
    if isinstance(v, int) and abs(v) > 10**15:
        if v.bit_length() < 14000:  # str() refuses more than 4300 digits
            return f"an integer of {len(str(abs(v)))} digits"
        return f"an integer of about {int(v.bit_length() * math.log10(2)) + 1} digits"
    return f"{v:g}" if isinstance(v, float) else str(v)


_BARE = re.compile(r"[A-Za-z0-9_-]+")


def key_path(field: str, key: str) -> str:
    """`field.key` for a message, the key quoted as TOML does when it is not bare (so a key
    with a dot, a space or a newline cannot break the one line or fake a field)."""
    k = key if _BARE.fullmatch(key) else json.dumps(key)
    return f"{field}.{k}" if field else k


class _Ctx:
    def __init__(self, src: str):
        self.src = src

    def fail(self, field: str, msg: str):
        raise SceneError(f"{self.src}: {field}: {msg}")

    # ---- typed getters ----
    def table(self, d: dict, allowed: set[str], required: set[str], field: str):
        if not isinstance(d, dict):
            self.fail(field, f"expected a table, got {type(d).__name__}")
        for k in d:
            if k not in allowed:
                self.fail(key_path(field, k),
                          f"unknown key (allowed: {', '.join(sorted(allowed))})")
        for k in sorted(required):
            if k not in d:
                self.fail(key_path(field, k), "missing required field")

    def number(self, v: Any, field: str, rng: Range = ANY, *, positive=False,
               nonneg=False) -> float:
        """A finite float in `rng` (and > 0 / >= 0 with `positive` / `nonneg`)."""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(field, f"expected a number, got {type(v).__name__}")
        if isinstance(v, float) and not math.isfinite(v):
            self.fail(field, f"must be finite, got {v}")
        if positive and not v > 0:
            self.fail(field, f"must be > 0, got {_fmt(v)}")
        if nonneg and v < 0:
            self.fail(field, f"must be >= 0, got {_fmt(v)}")
        # compare before converting: float() of an integer beyond 1.8e308 raises
        if (not (rng.lo < v if rng.lo_open else rng.lo <= v)
                or not (v < rng.hi if rng.hi_open else v <= rng.hi)):
            self.fail(field, f"must lie in {rng.text()}, got {_fmt(v)}")
        return float(v)

    def integer(self, v: Any, field: str, lo: int = 1, hi: int | None = None) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(field, f"expected an integer, got {type(v).__name__}")
        if v < lo:
            self.fail(field, f"must be >= {lo}, got {_fmt(v)}")
        if hi is not None and v > hi:
            self.fail(field, f"must be <= {hi}, got {_fmt(v)}")
        return v

    def vec(self, v: Any, field: str, n: int = 3, rng: Range = ANY) -> np.ndarray:
        if not isinstance(v, list) or len(v) != n:
            self.fail(field, f"expected a list of {n} numbers")
        return np.array([self.number(x, f"{field}[{i}]", rng) for i, x in enumerate(v)])

    def spectrum(self, v: Any, field: str, rng: Range = ANY, *, positive=False) -> np.ndarray:
        if isinstance(v, list):
            if len(v) != CHANNELS:
                self.fail(field, f"expected a number or a list of {CHANNELS} numbers")
            vals = [self.number(x, f"{field}[{i}]", rng, nonneg=True) for i, x in enumerate(v)]
        else:
            vals = [self.number(v, field, rng, nonneg=True)] * CHANNELS
        a = np.array(vals)
        if positive and not np.any(a > 0):
            self.fail(field, "must be > 0 in some channel")
        return a

    def boolean(self, v: Any, field: str) -> bool:
        if not isinstance(v, bool):
            self.fail(field, f"expected true or false, got {type(v).__name__}")
        return v

    def string(self, v: Any, field: str, choices=None) -> str:
        if not isinstance(v, str):
            self.fail(field, f"expected a string, got {type(v).__name__}")
        if choices is not None and v not in choices:
            self.fail(field, f"unknown value {v!r} (one of: {', '.join(choices)})")
        return v

    def unit(self, v: Any, field: str, rng: Range = DIRECTION) -> np.ndarray:
        """A direction: three numbers, not all zero, normalised (scaled by the largest
        component first, so tiny or huge components neither underflow nor overflow)."""
        a = self.vec(v, field, rng=rng)
        m = np.max(np.abs(a))
        if not m > 0:
            self.fail(field, "must be a non-zero vector")
        a = a / m
        return a / np.linalg.norm(a)


def _decode_error(e: UnicodeDecodeError) -> str:
    return (f"encoding: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset "
            f"{e.start}); TOML files must be UTF-8")


def read_toml(src: str, error: type[Exception] = SceneError) -> dict:
    """The parsed TOML document at `src`. Anything that keeps it from being read (missing
    file, a directory, a device or FIFO, more than `MAX_FILE_BYTES`, no permission, not
    UTF-8, a syntax error, nesting too deep for the parser) is an `error` (default
    `SceneError`) whose one line names `src`. A leading UTF-8 byte-order mark is skipped."""
    try:
        st = os.stat(src)  # before opening: opening a FIFO would block
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{src}: not a regular file (a device, FIFO or socket)")
        if st.st_size > MAX_FILE_BYTES:
            raise error(f"{src}: {st.st_size} bytes, more than a scene file's "
                        f"{MAX_FILE_BYTES} (is it the right file?)")
        with open(src, "rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise error(f"{src}: file not found") from None
    except IsADirectoryError:
        raise error(f"{src}: is a directory, not a TOML file") from None
    except OSError as e:
        raise error(f"{src}: cannot read: {e.strerror or e}") from None
    if len(data) > MAX_FILE_BYTES:
        raise error(f"{src}: more than a scene file's {MAX_FILE_BYTES} bytes")
    if data.startswith(b"\xef\xbb\xbf"):  # a UTF-8 byte-order mark (some editors write
        data = data[3:]                     # one): not part of the document
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{src}: {_decode_error(e)}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise error(f"{src}: TOML syntax: {e}") from None
    except RecursionError:
        raise error(f"{src}: TOML: arrays or tables nested too deeply") from None
