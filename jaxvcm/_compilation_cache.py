"""Persistent XLA compilation cache for the command line, fits and benchmarks, so that
repeated runs load compiled programs instead of recompiling them."""

from __future__ import annotations

import os

import jax

from . import _warm


def _cache_dir() -> str:
    d = os.environ.get("JAXVCM_CACHE_DIR")
    if d:
        return d
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxvcm", "jax")


def enable_compilation_cache(cache_dir: str | None = None) -> None:
    """Turn on JAX's persistent compilation cache, so that repeated runs do not recompile.

    Leaves an already configured cache (e.g. by a test harness) alone.

    `cache_dir` defaults to $JAXVCM_CACHE_DIR, else $XDG_CACHE_HOME/jaxvcm/jax (XDG_CACHE_HOME
    defaulting to ~/.cache). Never raises: a cache is an optimisation only.

    Also turns on exported warm starts (`_warm`: the lowered render pass is kept beside the
    cache, so a new process skips tracing it), but only when it configures the cache itself:
    a harness that configured its own (the test suite) keeps plain `jax.jit` passes."""
    try:
        if jax.config.jax_compilation_cache_dir:
            return
        d = cache_dir or _cache_dir()
        os.makedirs(d, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", d)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        _warm.enable()
    except Exception:  # a cache is an optimisation, never a reason to fail
        pass
