"""Test configuration: x64 available, strict dtype promotion, persistent compilation cache.

x64 is enabled so that float64 oracles and float64 renders are possible; the renderer's
own dtype comes from the scene (float32 by default), and strict promotion turns any
accidental float32/float64 mixing inside the kernels into an error.
"""

import os

# The suite is compile-bound (hundreds of small programs, each compiled once and run a few
# times at 16x16-ish sizes): XLA's CPU backend at LLVM optimisation level 0 compiles them
# about 25 % faster, and its code is slower only where a test runs many large passes. The
# arithmetic is the same IEEE arithmetic (no fast-math either way): the fixed-key renders of
# tests/test_golden.py, recorded at the default level, still agree to float32 round-off.
# Renders outside the tests keep the default level (docs/design.md: level 0 makes passes
# 2-3x slower). Set before jax is imported; subprocesses (the CLI tests) inherit it.
_flag = "--xla_backend_optimization_level=0"
if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
_cache = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".jax_cache")
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop in-memory compiled programs after each test module. A single pytest process
    otherwise keeps every executable of the whole suite alive (hundreds of programs, many
    GB); CI once aborted inside XLA while serialising an executable for the persistent
    cache late in the run. Later modules that need a program again get it back from the
    persistent cache."""
    yield
    jax.clear_caches()
    gc.collect()
