"""Exported warm starts (jaxvcm/_warm.py): the pass loaded from a serialized `jax.export`
module gives the same image and diagnostics bit for bit as the jitted pass, a new process
(here: a cleared memo) loads it from disk without tracing the renderer, and a change of
anything in the key (the config) exports a new module."""

from __future__ import annotations

import numpy as np
import pytest

import jaxvcm
from jaxvcm import _render, _warm

pytestmark = pytest.mark.skipif(not _warm.available(),
                                reason="needs flatbuffers (extra 'warm' / 'test')")

DOC = {
    "camera": {"position": [0.0, 1.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 40.0,
               "width": 6, "height": 4},
    "materials": {"m": {"type": "diffuse", "albedo": 0.6}},
    "shapes": [{"type": "rect", "center": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0],
                "size": [2.0, 2.0], "material": "m"}],
    "lights": [{"type": "sphere", "center": [0.0, 0.8, 1.0], "radius": 0.2, "radiance": 5.0}],
}


@pytest.fixture
def warm(tmp_path, monkeypatch):
    monkeypatch.setattr(_warm, "cache_root", str(tmp_path))
    monkeypatch.setattr(_warm, "_enabled", True)
    _warm.clear_memo()
    yield tmp_path
    _warm.clear_memo()


def test_exported_pass_equals_jitted_and_loads_without_tracing(warm, monkeypatch):
    scene = jaxvcm.scene_from_dict(DOC)
    cfg = jaxvcm.RenderConfig(algorithm="bdpt", max_depth=3)
    key = jaxvcm.pass_key(7, 2)
    ref_img, ref_diag = _render._render_pass_jit(scene, key, cfg, 2)
    assert _warm.enabled()
    img, diag, _ = _render.render_pass_host(scene, key, cfg, 2)
    # the same values: bit for bit under XLA's default settings; under the suite's compile
    # settings (`tests/conftest.py`: the elemental emitter, which may fuse the exported
    # module's wrapper differently) to float32 round-off (measured 1e-7 relative)
    np.testing.assert_allclose(np.asarray(img), np.asarray(ref_img), rtol=2e-6, atol=1e-9)
    assert np.asarray(img).sum() > 0
    for f in ("nonfinite", "camera_paths", "light_paths", "camera_vertices", "merge_overflow"):
        assert np.array_equal(np.asarray(getattr(diag, f)), np.asarray(getattr(ref_diag, f)))
    files = _warm.cached_files()
    assert len(files) == 1 and files[0].endswith(".jaxexport")
    # "a new process": nothing in memory, the renderer must not be traced again
    _warm.clear_memo()
    calls = []
    real = _render.render_pass
    monkeypatch.setattr(_render, "render_pass", lambda *a: calls.append(1) or real(*a))
    img2, _, _ = _render.render_pass_host(scene, key, cfg, 2)
    assert calls == [] and np.array_equal(np.asarray(img2), np.asarray(img))  # the same module
    # another pass index reuses the module; another config is another module
    _render.render_pass_host(scene, jaxvcm.pass_key(7, 3), cfg, 3)
    assert len(_warm.cached_files()) == 1
    _render.render_pass_host(scene, key, jaxvcm.RenderConfig(algorithm="pt", max_depth=3), 2)
    assert len(_warm.cached_files()) == 2


def test_corrupt_file_is_exported_again(warm):
    scene = jaxvcm.scene_from_dict(DOC)
    cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2)
    key = jaxvcm.pass_key(0, 0)
    a, _, _ = _render.render_pass_host(scene, key, cfg, 0)
    (f,) = _warm.cached_files()
    (warm / _warm.SUBDIR / f).write_bytes(b"not an export")
    _warm.clear_memo()
    b, _, _ = _render.render_pass_host(scene, key, cfg, 0)
    assert np.array_equal(np.asarray(a), np.asarray(b))
    assert (warm / _warm.SUBDIR / f).read_bytes() != b"not an export"


def test_off_without_a_cache_or_when_disabled(monkeypatch):
    monkeypatch.setattr(_warm, "_enabled", True)
    monkeypatch.setattr(_warm, "_root", lambda: None)
    assert not _warm.enabled()
    monkeypatch.setenv("JAXVCM_WARM_START", "0")
    _warm.enable()
    assert not _warm._enabled
