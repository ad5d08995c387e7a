"""Hostile input: every scene document either loads into a scene whose every
array is finite, or fails with ONE line 'FILE: FIELD: problem' (exit 2 on the CLI); never a
traceback, a NumPy warning, a NaN bound or a value stored as inf.

- A property test (hypothesis) mutates a document that uses every field of the schema
  (`FULL`: all shape, light and water fields) with hostile values: huge integers, numbers
  at and beyond float32's and float64's range, tiny and non-finite numbers, wrong types,
  nested arrays and tables, removed and unknown keys.
- Files that cannot be read as TOML: bad bytes anywhere (hypothesis), Latin-1, UTF-16, a
  directory, nesting deeper than the parser allows.
- Paths that cannot be written (`/proc`), fit configs, and the render-level rule that a
  render whose every contribution was non-finite does not exit 0 silently.
The malformed corpus tests/data/bad/ (test_cli.py) holds one file per hole found by hand.
"""

from __future__ import annotations

import copy
import os
import re
import types
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxvcm
from jaxvcm import SceneError
from jaxvcm.cli import main
from jaxvcm._io._toml import MAX_FILE_BYTES, read_toml

ROOT = Path(__file__).resolve().parents[2]
POOL = ROOT / "scenes" / "pool.toml"
SRC = "hostile.toml"

# A document with every field of the format (jaxvcm/_io/_scene_file.py's schema).
FULL = {
    "name": "full",
    "camera": {"position": [0.0, 3.0, 2.0], "target": [0.0, -1.0, 0.0], "up": [0.0, 1.0, 0.0],
               "fov": 40.0, "width": 8, "height": 6},
    "materials": {"floor": {"type": "diffuse", "albedo": [0.8, 0.7, 0.6]},
                  "wall": {"type": "diffuse", "albedo": 0.5},
                  "chrome": {"type": "mirror", "albedo": 0.9}},
    "shapes": [
        {"type": "basin", "min": [-1.0, -1.2, -1.0], "max": [1.0, 0.3, 1.0],
         "floor_material": "floor", "wall_material": "wall", "wall_tops": [0.3, 0.3, 0.2, 0.3]},
        {"type": "rect", "center": [0.0, 1.0, -1.5], "normal": [0.0, 0.0, 1.0],
         "size": [1.0, 0.5], "up": [0.0, 1.0, 0.0], "material": "chrome"},
        {"type": "sphere", "center": [0.5, -1.0, 0.5], "radius": 0.2, "material": "wall"},
    ],
    "water": {"level": 0.0, "waves": [[0.01, 11.0, 6.0, 0.0], [0.005, -5.0, 14.0, 1.3]],
              "sigma_a": [0.45, 0.07, 0.02], "sigma_s": 0.03, "phase": "hg", "g": 0.5,
              "b": 0.835, "ior": 1.33, "footprint": [-1.0, 1.0, -1.0, 1.0], "floor": -1.2},
    "lights": [
        {"type": "rect", "center": [0.25, 3.0, -0.25], "normal": [0.0, -1.0, 0.0],
         "size": [0.15, 0.15], "radiance": 1200.0, "up": [1.0, 0.0, 0.0], "albedo": 0.2},
        {"type": "sphere", "center": [-0.5, 2.0, 0.0], "radius": 0.05, "radiance": [5.0, 4, 3],
         "albedo": [0.1, 0.1, 0.1]},
        {"type": "sun", "direction": [0.3, -1.0, 0.2], "irradiance": 2.0},
        {"type": "sky", "radiance": 0.1},
    ],
}

# one line: 'hostile.toml: FIELD: problem', FIELD a dotted path of bare or "quoted" keys
# with [i] indices (or TOML / encoding for a file that does not parse)
_KEY = r'(?:[A-Za-z0-9_-]+|"(?:[^"\\]|\\.)*")(?:\[\d+\])*'
ONE_LINE = re.compile(rf"^hostile\.toml: (?:{_KEY}(?:\.{_KEY})*|TOML|encoding): \S.*$")


def _paths(node, prefix=()):
    """Every path into the document: tables' keys, arrays' indices, leaves and containers."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


PATHS = [p for p in _paths(FULL) if p]


def _nested(depth, leaf=1.0, kind="array"):
    v = leaf
    for _ in range(depth):
        v = [v] if kind == "array" else {"a": v}
    return v


HOSTILE = st.one_of(
    st.integers(min_value=-(10**500), max_value=10**500),
    st.sampled_from([10**400, -(10**400), 10**309, 2**1024, 10**30, 10**19, 2**31, 0, -1]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 3.5e38, 3.4e38, -3.5e38, 1e39, 1e-308, 5e-324, -0.0, 0.0,
                     1e-45, 1e-38, 1e-7, 1e6, 1e7, 1e15, 1e16, float("nan"), float("inf")]),
    st.booleans(),
    st.text(max_size=8),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5),
    st.lists(st.sampled_from([0.0, 1e-308, 1e308, -1e308, 10**400]), min_size=2, max_size=4),
    st.builds(_nested, st.integers(1, 60), st.sampled_from([1.0, 0.0, "x"]),
              st.sampled_from(["array", "table"])),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=3),
)


def _set(doc, path, value):
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _delete(doc, path):
    node = doc
    for k in path[:-1]:
        node = node[k]
    del node[path[-1]]


def _check_loaded_or_one_line(doc, src=SRC):
    """The property: a finite scene, or a SceneError of one line naming the file and field;
    with every warning an error (a NumPy RuntimeWarning fails the test)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            scene = jaxvcm.scene_from_dict(doc, src)
        except SceneError as e:
            msg = str(e)
            assert "\n" not in msg and ONE_LINE.match(msg), msg
            return msg
    for path, leaf in jax.tree_util.tree_flatten_with_path(scene)[0]:
        assert np.all(np.isfinite(np.asarray(leaf))), jax.tree_util.keystr(path)
    assert np.all(np.asarray(scene.bounds[1]) > np.asarray(scene.bounds[0]))
    return None


def test_full_document_loads():
    # the property's starting point uses every field and is valid
    assert _check_loaded_or_one_line(copy.deepcopy(FULL)) is None


# JAXVCM_HOSTILE_EXAMPLES=20000 for a longer hunt (the suite's 400 take about 3 s)
EXAMPLES = int(os.environ.get("JAXVCM_HOSTILE_EXAMPLES", "400"))


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(edits=st.lists(st.tuples(st.sampled_from(PATHS), HOSTILE, st.sampled_from(
    ["set", "set", "set", "delete", "unknown"])), min_size=1, max_size=3))
def test_hostile_documents(edits):
    doc = copy.deepcopy(FULL)
    for path, value, how in edits:
        try:
            if how == "set":
                _set(doc, path, value)
            elif how == "delete":
                _delete(doc, path)
            else:
                _set(doc, path[:-1] + ("zz_unknown",), value)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier edit removed or replaced the container
    _check_loaded_or_one_line(doc)


@pytest.mark.parametrize("field,value,expect", [
    # derived: the whole document stays valid except this one value
    (("camera", "position"), [10**400, 0, 0], "camera.position[0]"),
    (("camera", "fov"), 10**400, "camera.fov"),
    (("camera", "fov"), 1e-308, "camera.fov"),
    (("camera", "up"), [0.0, 0.0, -1e308], "camera.up[2]"),
    (("camera", "width"), 10**30, "camera.width"),
    (("water", "waves", 0, 1), 10**400, "water.waves[0][1]"),
    (("water", "sigma_a"), 3.5e38, "water.sigma_a"),
    (("water", "ior"), 1.0 - 1e-9, "water.ior"),
    (("water", "footprint", 1), 1e39, "water.footprint[1]"),
    (("shapes", 0, "max", 0), 1e39, "shapes[0].max[0]"),
    (("shapes", 1, "up"), [0.0, 0.0, 0.0], "shapes[1].up"),
    (("shapes", 1, "up"), [0.0, 0.0, -3.0], "shapes[1].up"),  # parallel to the normal
    (("lights", 0, "size"), [1e-308, 0.1], "lights[0].size[0]"),
    (("lights", 0, "albedo"), 2.0, "lights[0].albedo"),
    (("lights", 1, "radius"), 1e-308, "lights[1].radius"),
    (("lights", 1, "radiance"), 1e308, "lights[1].radiance"),
    (("lights", 2, "irradiance"), 10**400, "lights[2].irradiance"),
], ids=lambda v: v if isinstance(v, str) else None)
def test_reported_holes(field, value, expect):
    # each hole found by hand, on the full document: one line naming exactly this field
    doc = copy.deepcopy(FULL)
    _set(doc, field, value)
    msg = _check_loaded_or_one_line(doc)
    assert msg is not None and msg.startswith(f"{SRC}: {expect}: "), msg


@pytest.mark.parametrize("field,value,culprit", [
    (("water", "level"), 1e6, "water.level"),
    (("camera", "position"), [1e6, 1.0, 0.0], "camera.position"),
], ids=["water-level", "camera"])
def test_extent_set_by_one_field_is_named(field, value, culprit):
    # one far value makes the scene's extent huge and every light too small for float32
    # there: the line names the small light and what set the extent
    doc = copy.deepcopy(FULL)
    _set(doc, field, value)
    msg = _check_loaded_or_one_line(doc)
    assert msg is not None and f"extent (1e+06 m, set by {culprit})" in msg, msg


@pytest.mark.parametrize("ior", [1.0, 1.33, 3.0])
def test_documented_ior_range_accepted(ior):
    # ior in [1, 3]: 1 is an index-matched boundary (the medium furnaces use it)
    doc = copy.deepcopy(FULL)
    doc["water"]["ior"] = ior
    assert _check_loaded_or_one_line(doc) is None


# ------------------------------------------------------------------ files
def _cli_error(args, capsys) -> str:
    rc = main(args)
    _, err = capsys.readouterr()
    assert rc == 2, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    return lines[0]


@settings(max_examples=max(150, EXAMPLES // 3), deadline=None)
@given(pos=st.integers(0, 10**6), byte=st.integers(0, 255))
def test_any_byte_anywhere(pos, byte):
    # a byte overwritten anywhere in a valid file: the scene loads (finite) or one line
    data = bytearray(POOL.read_bytes())
    data[pos % len(data)] = byte
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / SRC
        p.write_bytes(bytes(data))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                scene = jaxvcm.load_scene(p)
        except SceneError as e:
            msg = str(e)
            assert msg.startswith(f"{p}: ") and "\n" not in msg, msg
            return
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(scene))


@pytest.mark.parametrize("encoding", ["latin-1", "utf-16", "utf-32"])
def test_not_utf8(encoding, tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_bytes(POOL.read_text().replace("pool", "piscine é", 1).encode(encoding))
    line = _cli_error(["info", str(p)], capsys)
    assert line.startswith(f"jaxvcm: error: {p}: encoding: not UTF-8 text (byte 0x"), line


@pytest.mark.parametrize("depth", [10, 500, 1000, 5000, 50000])
@pytest.mark.parametrize("kind", ["array", "table"])
def test_deep_nesting(kind, depth, tmp_path, capsys):
    # from about 800 levels the TOML parser itself recurses too deep (RecursionError);
    # below that, our validation names the field
    open_, close = ("[", "]") if kind == "array" else ("{a = ", "}")
    p = tmp_path / "s.toml"
    p.write_text(POOL.read_text().replace("fov = 42", "fov = " + open_ * depth + "1"
                                          + close * depth))
    line = _cli_error(["info", str(p)], capsys)
    assert (line.startswith(f"jaxvcm: error: {p}: camera.fov: expected a number, got ")
            or line == f"jaxvcm: error: {p}: TOML: arrays or tables nested too deeply"), line


def test_directory_as_scene(tmp_path, capsys):
    line = _cli_error(["info", str(tmp_path)], capsys)
    assert line == f"jaxvcm: error: {tmp_path}: is a directory, not a TOML file"
    with pytest.raises(SceneError, match="is a directory"):
        read_toml(str(tmp_path))


def test_byte_order_mark_is_skipped(tmp_path):
    p = tmp_path / "s.toml"
    p.write_bytes(b"\xef\xbb\xbf" + POOL.read_bytes())
    assert read_toml(str(p)) == read_toml(str(POOL))


def test_special_and_huge_files_one_line(tmp_path, capsys):
    # a FIFO (opening it would block), a device, a file past the size cap: one line each,
    # at once
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    big = tmp_path / "big.toml"
    with open(big, "wb") as f:
        f.truncate(MAX_FILE_BYTES + 1)
    for path, what in ((fifo, "not a regular file"), ("/dev/zero", "not a regular file"),
                       (big, f"more than a scene file's {MAX_FILE_BYTES}")):
        line = _cli_error(["info", str(path)], capsys)
        assert line.startswith(f"jaxvcm: error: {path}: ") and what in line, line


def test_base_naming_a_directory_one_line(tmp_path, capsys):
    (tmp_path / "d").mkdir()
    p = tmp_path / "s.toml"
    p.write_text('base = "d"\n' + POOL.read_text())
    line = _cli_error(["info", str(p)], capsys)
    assert line.startswith(f"jaxvcm: error: {p}: base: is a directory"), line


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc")
@pytest.mark.parametrize("args,out", [
    (["render", str(POOL), "--passes", "1", "--out", "/proc/x.exr"], "/proc/x.exr"),
    (["export", str(POOL), "/proc/x.obj"], "/proc/x.obj"),
], ids=["render", "export"])
def test_unwritable_output_named(args, out, capsys):
    # the user's path, not the temporary file beside it; and before any rendering
    line = _cli_error(args, capsys)
    assert line.startswith(f"jaxvcm: error: {out}: cannot write: "), line
    assert ".tmp" not in line


@pytest.mark.parametrize("flag,value", [
    ("--width", "100000"), ("--width", "16385"), ("--height", "1" + "0" * 30),
    ("--width", "7" * 500),
    ("--exposure", "1e308"), ("--seed", str(10**30)), ("--max-depth", "100000"),
    ("--radius", "1e308"), ("--width", "1e3"),
])
def test_cli_ranges(flag, value, capsys):
    line = _cli_error(["render", str(POOL), flag, value], capsys)
    assert line.startswith(f"jaxvcm: error: argument {flag}: "), line
    assert len(line) < 200


def _fit_config(tmp_path, override: str) -> Path:
    p = tmp_path / "fit.toml"
    p.write_text(f"""
[scenes.a]
file = "{POOL}"
override = {override}
[[regions]]
name = "r"
scene = "a"
rect = [0, 0, 4, 4]
target = [0.1, 0.2, 0.3]
[render]
width = 8
height = 8
""")
    return p


@pytest.mark.parametrize("override,field", [
    ("{ camera = { fov = 1" + "0" * 400 + " } }", "camera.fov"),
    ("{ water = { sigma_a = 1e39 } }", "water.sigma_a"),
    ("{ lights = [ { type = 'sky', radiance = 1e308 } ] }", "lights[0].radiance"),
], ids=["huge-int", "float32", "radiance"])
def test_fit_override_errors(override, field, tmp_path, capsys):
    cfg = _fit_config(tmp_path, override)
    line = _cli_error(["fit", str(cfg), "--out", str(tmp_path / "o")], capsys)
    # named as the fit config's override, where the value was written
    assert line.startswith(f"jaxvcm: error: {cfg}: scenes.a.override.{field}: "), line
    assert not (tmp_path / "o").exists()


def test_scene_file_given_to_fit(capsys):
    line = _cli_error(["fit", str(POOL)], capsys)
    assert line == (f"jaxvcm: error: {POOL}: a scene file, not a fit config (a fit config "
                    "names its scenes in [scenes.NAME] and its targets in [[regions]])"), line


def test_fit_config_not_utf8(tmp_path, capsys):
    cfg = _fit_config(tmp_path, "{}")
    cfg.write_bytes(cfg.read_bytes() + b"# \xff\n")
    line = _cli_error(["fit", str(cfg)], capsys)
    assert line.startswith(f"jaxvcm: error: {cfg}: encoding: not UTF-8 text (byte 0xff"), line


# ------------------------------------------------------------------ renders
def _fake_passes(monkeypatch, value, nonfinite):
    """render_pass_host replaced by passes of constant `value` with `nonfinite` zeroed
    contributions each: the render-level rules without compiling a renderer."""
    import jaxvcm._render as R

    def fake(scene, key, config, pass_index=0):
        H, W = scene.camera.height, scene.camera.width
        img = np.full((H, W, scene.channels), value, np.float32)
        return img, types.SimpleNamespace(nonfinite=nonfinite), config

    monkeypatch.setattr(R, "render_pass_host", fake)


@pytest.mark.parametrize("value,nonfinite,rc,lines", [
    (0.0, 75, 3, ["150 non-finite path contributions were zeroed",
                  "the image is black: every path contribution was non-finite"]),
    (0.5, 2, 0, ["4 non-finite path contributions were zeroed"]),
    (0.0, 0, 0, ["the image is black: no path contribution reached the film"]),
    (0.5, 0, 0, []),
], ids=["all-nonfinite", "some-nonfinite", "black", "ok"])
def test_render_warnings_and_exit(value, nonfinite, rc, lines, monkeypatch, tmp_path, capsys):
    # 2 passes: nonfinite counts add up; every warning is one line on stderr and in the JSON
    import json

    _fake_passes(monkeypatch, value, nonfinite)
    out = tmp_path / "r.exr"
    got = main(["render", str(POOL), "--passes", "2", "--width", "4", "--height", "4",
                "--quiet", "--out", str(out)])
    _, err = capsys.readouterr()
    assert got == rc, err
    assert err.splitlines() == [f"jaxvcm: warning: {w}" for w in lines]
    assert json.loads(out.with_suffix(".json").read_text())["warnings"] == lines
    assert jaxvcm.check_outputs(str(out)) == []
