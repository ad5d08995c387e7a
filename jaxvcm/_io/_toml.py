"""Reading a TOML file and validating its values, with one-line errors
'FILE: FIELD: problem' that name the offending field (`SceneError`, `_Ctx`)."""

from __future__ import annotations

import math
import tomllib
from typing import Any

import numpy as np

CHANNELS = 3


class SceneError(ValueError):
    """A malformed scene file. str() is one line: 'FILE: FIELD: problem'."""


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
                self.fail(f"{field}.{k}" if field else k,
                          f"unknown key (allowed: {', '.join(sorted(allowed))})")
        for k in sorted(required):
            if k not in d:
                self.fail(f"{field}.{k}" if field else k, "missing required field")

    def number(self, v: Any, field: str, *, positive=False, nonneg=False) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(field, f"expected a number, got {type(v).__name__}")
        v = float(v)
        if not math.isfinite(v):
            self.fail(field, f"must be finite, got {v}")
        if positive and not v > 0:
            self.fail(field, f"must be > 0, got {v}")
        if nonneg and v < 0:
            self.fail(field, f"must be >= 0, got {v}")
        return v

    def integer(self, v: Any, field: str, lo: int = 1) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(field, f"expected an integer, got {type(v).__name__}")
        if v < lo:
            self.fail(field, f"must be >= {lo}, got {v}")
        return v

    def vec(self, v: Any, field: str, n: int = 3) -> np.ndarray:
        if not isinstance(v, list) or len(v) != n:
            self.fail(field, f"expected a list of {n} numbers")
        return np.array([self.number(x, f"{field}[{i}]") for i, x in enumerate(v)])

    def spectrum(self, v: Any, field: str, *, positive=False) -> np.ndarray:
        if isinstance(v, list):
            if len(v) != CHANNELS:
                self.fail(field, f"expected a number or a list of {CHANNELS} numbers")
            vals = [self.number(x, f"{field}[{i}]", nonneg=True) for i, x in enumerate(v)]
        else:
            vals = [self.number(v, field, nonneg=True)] * CHANNELS
        a = np.array(vals)
        if positive and not np.any(a > 0):
            self.fail(field, "must be > 0 in some channel")
        return a

    def string(self, v: Any, field: str, choices=None) -> str:
        if not isinstance(v, str):
            self.fail(field, f"expected a string, got {type(v).__name__}")
        if choices is not None and v not in choices:
            self.fail(field, f"unknown value {v!r} (one of: {', '.join(choices)})")
        return v

    def unit(self, v: Any, field: str) -> np.ndarray:
        a = self.vec(v, field)
        n = np.linalg.norm(a)
        if n == 0:
            self.fail(field, "must be a non-zero vector")
        return a / n


def read_toml(src: str) -> dict:
    """The parsed TOML document at `src`; a missing file or a syntax error is a `SceneError`."""
    try:
        with open(src, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise SceneError(f"{src}: file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{src}: TOML syntax: {e}") from None
