"""The scene-file schema (`jaxvcm._io._schema`) is the format that is enforced, and the
reference page is generated from it.

- docs/scene-format.md equals the text generated from the schema (regenerate with
  `python -m jaxvcm._io._scene_format docs/scene-format.md`).
- Every bound of every ranged number in the schema (each field, per type; a vector's first
  component, a spectrum's first channel, each component of a wave): a value just outside
  is refused with one line naming the field; the bound itself (just inside an open bound)
  is accepted. Where other rules make a bound unreachable (a basin's `min` at the largest
  coordinate has no `max` above it), the scene fails naming that rule's field instead.
- The keys each table and type accepts and requires, the enum choices and the defaults
  are the schema's.
"""

from __future__ import annotations

import copy
import math
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxvcm
from jaxvcm import SceneError
from jaxvcm._io import _schema as S

ROOT = Path(__file__).resolve().parents[2]
SRC = "schema.toml"

# Every table and type of the format with every optional field given, sized so that most
# bounds are reachable: every shape at least 4 m (>= 1e-6 x an extent of 3.5e6 m).
DOC = {
    "name": "schema",
    "camera": {"position": [0.0, 20.0, 20.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
               "fov": 40.0, "width": 8, "height": 6},
    "materials": {
        "diffuse": {"type": "diffuse", "albedo": 0.5},
        "mirror": {"type": "mirror", "albedo": 0.9},
        "glass": {"type": "glass", "ior": 1.5},
        "glossy": {"type": "glossy", "albedo": 0.0, "glossy": 0.0, "exponent": 50.0},
    },
    "shapes": [
        {"type": "basin", "min": [-4.0, -4.0, -4.0], "max": [4.0, 1.0, 4.0],
         "floor_material": "diffuse", "wall_material": "diffuse", "wall_tops": [1.0, 1.0, 1.0, 1.0],
         "two_sided": True},
        {"type": "rect", "center": [0.0, 2.0, -10.0], "normal": [0.0, 0.0, 1.0], "size": [4.0, 4.0],
         "up": [0.0, 1.0, 0.0], "material": "mirror", "two_sided": True},
        {"type": "sphere", "center": [10.0, 0.0, 0.0], "radius": 4.0, "material": "glossy",
         "two_sided": True},
    ],
    "water": {"level": 0.0, "waves": [[0.01, 11.0, 6.0, 0.0]], "sigma_a": [0.45, 0.07, 0.02],
              "sigma_s": 0.03, "phase": "hg", "g": 0.5, "b": 0.835, "ior": 1.33,
              "footprint": [-4.0, 4.0, -4.0, 4.0], "floor": -3.9},
    "lights": [
        {"type": "rect", "center": [0.0, 10.0, 0.0], "normal": [0.0, -1.0, 0.0], "size": [4.0, 4.0],
         "up": [0.0, 0.0, 1.0], "radiance": 100.0, "albedo": 0.2},
        {"type": "sphere", "center": [-10.0, 10.0, 0.0], "radius": 4.0, "radiance": 5.0,
         "albedo": 0.1},
        {"type": "sun", "direction": [0.3, -1.0, 0.2], "irradiance": 2.0, "aim": 0.5},
        {"type": "sky", "radiance": 0.1, "aim": 0.3},
        {"type": "point", "position": [0.0, 5.0, 0.0], "intensity": 3.0},
    ],
}
SKY = 3  # the sky's index: replaced by the background (at most one of the two)

# Bounds that other rules make unreachable: the message (field: start) the scene fails with.
UNREACHABLE = {
    "water.level-lo": "water.floor: must lie below the lowest point of the water surface",
    "water.floor-hi": "water.floor: must lie below the lowest point of the water surface",
    "water.footprint[0]-hi": "water.footprint: zero-size shape",
    "shapes[0].min[0]-hi": "shapes[0].max: zero-size shape",
    "shapes[0].max[0]-lo": "shapes[0].max: zero-size shape",
    "shapes[0].wall_tops[0]-lo": "shapes[0].wall_tops: every wall top must be above the floor",
    "shapes[1].size[0]-lo": "shapes[1].size: 1e-06 m is below 1e-06 x the scene's extent",
    "shapes[2].radius-lo": "shapes[2].radius: 1e-06 m is below 1e-06 x the scene's extent",
    "lights[0].size[0]-lo": "lights[0].size: 1e-06 m is below 1e-06 x the scene's extent",
    "lights[1].radius-lo": "lights[1].radius: 1e-06 m is below 1e-06 x the scene's extent",
}
# Bounds reachable with other fields moved: a wave's amplitude of 1e6 m over deep water.
DEEP = {("water", "level"): 5e5, ("water", "floor"): -6e5}
ALSO = {"water.waves[0][0]-lo": DEEP, "water.waves[0][0]-hi": DEEP}


def _entries():
    """(table, type, path into DOC, the field prefix of messages) for each table and type."""
    yield S.CAMERA, None, ("camera",), "camera"
    for v in S.MATERIALS.variants:
        yield S.MATERIALS, v, ("materials", v.type), f"materials.{v.type}"
    for t in (S.SHAPES, S.LIGHTS):
        for v in t.variants:
            i = SKY if v.type == "background" else next(
                i for i, e in enumerate(DOC[t.name]) if e["type"] == v.type)
            yield t, v, (t.name, i), f"{t.name}[{i}]"
    yield S.WATER, None, ("water",), "water"


def _doc(variant=None) -> dict:
    doc = copy.deepcopy(DOC)
    if variant is not None and variant.type == "background":
        doc["lights"][SKY] = {"type": "background", "radiance": 0.1}
    return doc


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _set(doc, path, value):
    _get(doc, path[:-1])[path[-1]] = value


def _load(doc):
    """The scene, or the SceneError's message (checked to be one line); warnings fail."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return jaxvcm.scene_from_dict(doc, SRC)
        except SceneError as e:
            msg = str(e)
            assert "\n" not in msg and msg.startswith(f"{SRC}: "), msg
            return msg


def _ranged():
    """(id, variant, path into the document, value at a bound -> (outside, inside)) for
    every bound of every ranged number of the schema."""
    for table, variant, path, prefix in _entries():
        fields = variant.fields if variant is not None else table.fields
        if table is S.SHAPES:
            fields = variant.all_fields()
        for f in fields:
            if f.items:  # each wave's components
                items = [(f"{prefix}.{f.name}[0][{i}]", path + (f.name, 0, i), c)
                         for i, c in enumerate(f.items)]
            elif f.range is None:
                continue
            elif f.kind in ("vector", "direction"):
                items = [(f"{prefix}.{f.name}[0]", path + (f.name, 0), f)]
            elif f.kind == "spectrum":  # the first channel of a list
                items = [(f"{prefix}.{f.name}[0]", path + (f.name,), f)]
            else:
                items = [(f"{prefix}.{f.name}", path + (f.name,), f)]
            for name, p, c in items:
                r = c.range
                for side in ("lo", "hi"):
                    yield f"{name}-{side}", variant, p, c, _bound(c, r, side)


def _bound(f, r, side):
    """(just outside, at or just inside) the bound `side` of range `r`."""
    b, out = (r.lo, -math.inf) if side == "lo" else (r.hi, math.inf)
    open_ = r.lo_open if side == "lo" else r.hi_open
    if f.kind == "integer":
        step = -1 if side == "lo" else 1
        return int(b) + step, int(b)
    if open_:
        return b, float(np.nextafter(b, -out))
    return float(np.nextafter(b, out)), b


RANGED = list(_ranged())


def _with_value(case, value):
    name, variant, path, f, _ = case
    doc = _doc(variant)
    for p, v in ALSO.get(name, {}).items():
        _set(doc, p, v)
    if f.kind == "spectrum":
        mid = 0.5 * (f.range.lo + f.range.hi)
        value = [value, mid, mid]
    _set(doc, path, value)
    return doc


def test_page_is_generated():
    # the committed page is the schema's
    page = (ROOT / "docs" / "scene-format.md").read_text(encoding="utf-8")
    assert page == S.format_markdown(str(ROOT)), (
        "docs/scene-format.md is stale: python -m jaxvcm._io._scene_format docs/scene-format.md")


def test_document_loads():
    for variant in (None, S.LIGHTS.variant("background")):
        assert not isinstance(_load(_doc(variant)), str)


def test_every_field_covered():
    # DOC gives every field of the schema (so the cases below reach all of them)
    for table, variant, path, _ in _entries():
        fields = variant.all_fields() if variant is not None else table.fields
        assert {f.name for f in fields} == set(_get(_doc(variant), path)), path


@pytest.mark.parametrize("case", RANGED, ids=[c[0] for c in RANGED])
def test_outside_the_range_is_refused(case):
    name = case[0].rsplit("-", 1)[0]
    outside, _ = case[4]
    msg = _load(_with_value(case, outside))
    assert isinstance(msg, str), f"{outside!r} accepted"
    assert msg.startswith(f"{SRC}: {name}: "), msg


@pytest.mark.parametrize("case", RANGED, ids=[c[0] for c in RANGED])
def test_the_bound_is_accepted(case):
    _, inside = case[4]
    got = _load(_with_value(case, inside))
    if case[0] in UNREACHABLE:
        assert isinstance(got, str) and got.startswith(f"{SRC}: {UNREACHABLE[case[0]]}"), got
    else:
        assert not isinstance(got, str), got


def _typed():
    for table, variant, path, prefix in _entries():
        yield prefix, variant if variant is not None else table, variant, path


TYPED = list(_typed())


@pytest.mark.parametrize("prefix,spec,variant,path", TYPED, ids=[t[0] for t in TYPED])
def test_accepted_keys(prefix, spec, variant, path):
    # an unknown key is refused naming the schema's keys (materials: those of any type
    # first); a key of another type is refused naming this type's keys
    doc = _doc(variant)
    _get(doc, path)["zz"] = 1.0
    table = S.MATERIALS if path[0] == "materials" else spec
    keys = table.keys() if path[0] == "materials" else spec.keys()
    assert _load(doc) == f"{SRC}: {prefix}.zz: unknown key (allowed: {', '.join(sorted(keys))})"
    if variant is not None:
        others = sorted((S.MATERIALS if path[0] == "materials" else
                         (S.SHAPES if path[0] == "shapes" else S.LIGHTS)).keys() - spec.keys())
        for k in others:
            doc = _doc(variant)
            _get(doc, path)[k] = 1.0
            msg = _load(doc)
            assert msg == (f"{SRC}: {prefix}.{k}: unknown key (allowed: "
                           f"{', '.join(sorted(spec.keys()))})"), msg


@pytest.mark.parametrize("prefix,spec,variant,path", TYPED, ids=[t[0] for t in TYPED])
def test_required_keys(prefix, spec, variant, path):
    for k in sorted(spec.required() - {"type"}):
        doc = _doc(variant)
        del _get(doc, path)[k]
        assert _load(doc) == f"{SRC}: {prefix}.{k}: missing required field"
    # and nothing else is required (a field with a computed default needs the basin)
    doc = _doc(variant)
    entry = _get(doc, path)
    for f in (variant.all_fields() if variant is not None else spec.fields):
        if not f.required:
            del entry[f.name]
    assert not isinstance(_load(doc), str)


def test_top_level_keys():
    doc = _doc()
    doc["zz"] = 1
    assert _load(doc) == (f"{SRC}: zz: unknown key (allowed: "
                          f"{', '.join(sorted(S.DOCUMENT.keys()))})")
    for k in sorted(S.DOCUMENT.required()):
        doc = _doc()
        del doc[k]
        assert _load(doc) == f"{SRC}: {k}: missing required field"


ENUMS = [("materials.diffuse.type", ("materials", "diffuse", "type"), S.MATERIALS["type"]),
         ("shapes[0].type", ("shapes", 0, "type"), S.SHAPES["type"]),
         ("lights[0].type", ("lights", 0, "type"), S.LIGHTS["type"]),
         ("water.phase", ("water", "phase"), S.WATER["phase"])]


@pytest.mark.parametrize("name,path,f", ENUMS, ids=[e[0] for e in ENUMS])
def test_enum_choices(name, path, f):
    doc = _doc()
    _set(doc, path, "zz")
    assert _load(doc) == f"{SRC}: {name}: unknown value 'zz' (one of: {', '.join(f.choices)})"


@pytest.mark.parametrize("phase", S.WATER["phase"].choices)
def test_every_phase_accepted(phase):
    doc = _doc()
    doc["water"]["phase"] = phase
    assert not isinstance(_load(doc), str)


def _defaulted():
    for table, variant, path, prefix in _entries():
        for f in (variant.all_fields() if variant is not None else table.fields):
            if not f.required and not isinstance(f.default, S.Derived):
                yield f"{prefix}.{f.name}", variant, path, f


DEFAULTED = list(_defaulted())


@pytest.mark.parametrize("name,variant,path,f", DEFAULTED, ids=[d[0] for d in DEFAULTED])
def test_defaults(name, variant, path, f):
    # a field left out is the schema's default
    given, left_out = _doc(variant), _doc(variant)
    _get(given, path)[f.name] = copy.deepcopy(f.default)
    del _get(left_out, path)[f.name]
    a, b = _load(given), _load(left_out)
    assert not isinstance(a, str) and not isinstance(b, str), (a, b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
