"""Persistent XLA compilation cache for the command line, fits and benchmarks, so that
repeated runs load compiled programs instead of recompiling them."""

from __future__ import annotations

import os

import jax


def _cache_dir() -> str:
    d = os.environ.get("JAXVCM_CACHE_DIR")
    if d:
        return d
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxvcm", "jax")


def enable_compilation_cache(cache_dir: str | None = None) -> None:
    """Persistent XLA compilation cache, so repeated CLI renders do not recompile.
    Leaves an already configured cache (e.g. by a test harness) alone.

    `cache_dir` defaults to $JAXVCM_CACHE_DIR, else $XDG_CACHE_HOME/jaxvcm/jax (XDG_CACHE_HOME
    defaulting to ~/.cache). Never raises: a cache is an optimisation only."""
    try:
        if jax.config.jax_compilation_cache_dir:
            return
        d = cache_dir or _cache_dir()
        os.makedirs(d, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", d)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except Exception:  # a cache is an optimisation, never a reason to fail
        pass
