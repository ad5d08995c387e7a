"""Warm starts: the host driver's pass kept as a serialized `jax.export` module.

JAX's persistent compilation cache skips XLA's compilation in a new process, but not the
tracing and lowering that produce the module it is keyed by, a large part of a warm first
pass (docs/benchmarks.md has the startup figures). This module stores the lowered pass
itself (`jax.export.export(...).serialize()`) next to the compilation cache, so a later
process deserializes it and goes straight to the cached executable: no Python tracing of
the renderer at all.

The pass is exported as a function of flat arrays (the scene's leaves, the key's raw data,
the pass index as int32), so its signature needs no custom pytree serialization; the
scene's tree structure and the static `RenderConfig` are part of the file's key, with the
shapes and dtypes of the leaves, the backend, the versions of jax and jaxlib and a hash of
jaxvcm's own source files: any change to the renderer gives a new key, never a stale
module. Files are written atomically; an unreadable one is ignored and rewritten.

Used by `render_pass_host` (CLI renders, `jaxvcm.render`) once
`enable_compilation_cache` has turned the persistent cache on (the CLI, fits and
benchmarks do) and `flatbuffers` (jax.export's serializer; the optional extra `warm`) is
installed; otherwise the pass is plain `jax.jit` and nothing is written.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from pathlib import Path

import jax
import jaxlib
import numpy as np
from jax import export as jax_export

from ._io import atomic_path

_enabled = False
_memo: dict[str, object] = {}
SUBDIR = "jaxvcm-exported"
cache_root: str | None = None  # default: JAX's persistent compilation cache directory


def _root() -> str | None:
    return cache_root or jax.config.jax_compilation_cache_dir


def enable(on: bool = True) -> None:
    """Turn exported warm starts on (`enable_compilation_cache` does) or off; the
    environment variable JAXVCM_WARM_START=0 keeps them off."""
    global _enabled
    _enabled = bool(on) and os.environ.get("JAXVCM_WARM_START", "1") != "0"


@functools.cache
def available() -> bool:
    """jax.export's serialization needs the optional `flatbuffers` (extra `warm`)."""
    try:
        import flatbuffers  # noqa: F401
    except ImportError:
        return False
    return True


def enabled() -> bool:
    return _enabled and bool(_root()) and available()


def _cache_dir() -> Path | None:
    d = _root()
    return Path(d) / SUBDIR if (_enabled and d) else None


@functools.cache
def _source_hash() -> str:
    """SHA-256 over every file of the jaxvcm package (sources and shipped data: path and
    content; bytecode caches left out), once per process."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for p in sorted(root.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _signature(treedef, leaves, config, what: str) -> str:
    # what shapes the lowered program: the code, jax, the backend, the config flags that
    # change dtypes or promotion, the static config, the scene's structure and leaf types
    parts = [what, _source_hash(), jax.__version__, jaxlib.__version__, jax.default_backend(),
             str(jax.config.jax_enable_x64), str(jax.config.jax_numpy_dtype_promotion),
             repr(config), str(treedef),
             repr([(tuple(np.shape(x)), str(np.asarray(x).dtype) if not hasattr(x, "dtype")
                    else str(x.dtype)) for x in leaves])]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:40]


def _load_or_export(path: Path | None, build):
    """The exported module at `path` (deserialized), else `build()` exported and stored."""
    if path is not None and path.is_file():
        try:
            return jax_export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 (a truncated or foreign file: export anew)
            pass
    exp = build()
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(str(path)) as tmp:
                Path(tmp).write_bytes(exp.serialize())
        except OSError:  # a cache is an optimisation, never a reason to fail
            pass
    return exp


def exported_pass(pass_fn, out_type, scene, key, config, pass_index):
    """`pass_fn(scene, key, config, pass_index) -> (image, out_type(*arrays))` run through
    an exported module (loaded from the cache when there is one); the same values as
    `jax.jit(pass_fn, static_argnums=2)` would give. `out_type` is an `eqx.Module` of
    arrays only, rebuilt from its fields in order."""
    leaves, treedef = jax.tree_util.tree_flatten(scene)
    kdata = jax.random.key_data(key)
    impl = jax.random.key_impl(key)
    idx = np.int32(pass_index)
    sig = _signature(treedef, leaves + [kdata, idx], config, f"pass:{impl}")
    fn = _memo.get(sig)
    if fn is None:
        d = _cache_dir()
        fields = [f.name for f in dataclasses.fields(out_type)]

        def flat_pass(leaves, kdata, idx):
            s = jax.tree_util.tree_unflatten(treedef, leaves)
            img, aux = pass_fn(s, jax.random.wrap_key_data(kdata, impl=impl), config, idx)
            return img, tuple(getattr(aux, f) for f in fields)

        def build():
            return jax_export.export(jax.jit(flat_pass))(leaves, kdata, idx)

        exp = _load_or_export(None if d is None else d / f"pass-{sig}.jaxexport", build)
        fn = jax.jit(exp.call)
        _memo[sig] = fn
    img, arrays = fn(leaves, kdata, jax.device_put(idx))
    return img, out_type(*arrays)


def clear_memo() -> None:
    """Forget this process's loaded modules (tests: force the load from disk)."""
    _memo.clear()


def cached_files() -> list[str]:
    d = _cache_dir()
    return sorted(os.listdir(d)) if d is not None and d.is_dir() else []
