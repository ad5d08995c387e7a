"""The scene-file format as one declarative schema.

Every section, field, kind, unit, valid range, default and enum choice of a scene file is
declared here once. The loader reads them from here (`_scene_sections.py`: the ranges it
enforces, the defaults it fills in, the choices and the keys each table accepts), and the
reference page docs/scene-format.md is generated from here (`format_markdown`), so the
page and the validation cannot disagree. Regenerate the page with

    python -m jaxvcm._io._scene_format docs/scene-format.md

(tests/io/test_schema.py checks that the committed page equals the generated text and that
every range declared here is the one enforced).
"""

from __future__ import annotations

import dataclasses
import os
import re
from typing import Any

CHANNELS = 3  # the channels of a spectrum (RGB)


@dataclasses.dataclass(frozen=True)
class Range:
    """The valid values of a number: lo <= x <= hi (`lo_open`: lo < x; `hi_open`: x < hi),
    in `unit` (the unit shown in error messages)."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, x: float) -> bool:
        return ((x > self.lo if self.lo_open else x >= self.lo)
                and (x < self.hi if self.hi_open else x <= self.hi))

    def text(self) -> str:
        u = f" {self.unit}" if self.unit else ""
        return (f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                f"{')' if self.hi_open else ']'}{u}")


# ---- the ranges: they keep every derived value finite in float32 (the renderer's precision)
MAX_LENGTH = 1e6  # metres: float32 resolves 0.06 m at 1e6 m; squares stay < 1e13
COORD = Range(-MAX_LENGTH, MAX_LENGTH, "m")
SIZE = Range(1e-6, MAX_LENGTH, "m")  # and >= REL_SIZE x the scene's extent
REL_SIZE = 1e-6  # 16 float32 ulps of the scene's extent: smaller shapes are not resolved
DIRECTION = Range(-MAX_LENGTH, MAX_LENGTH)  # components; normalised, must be non-zero
ANY = Range(-MAX_LENGTH, MAX_LENGTH)  # a number without its own range
FOV = Range(0.01, 179.0, "degrees")
MAX_FILE_BYTES = 16 << 20  # a scene or fit file is a few kB; none is read past this
MAX_PIXELS = 16384  # per side: a 16384^2 float32 RGB film is 3.2 GB; a pass of 2^28 paths
# keeps its path numbers and, in chunks (`_integrator.min_chunks`), its indices within int32
PIXELS = Range(1, MAX_PIXELS)
ALBEDO = Range(0.0, 1.0)  # materials and emitters alike (energy conservation)
RADIANCE = Range(0.0, 1e15, "W/(m^2 sr)")  # emitted power stays < 1e29 W
IRRADIANCE = Range(0.0, 1e15, "W/m^2")  # the sun's
INTENSITY = Range(0.0, 1e15, "W/sr")  # a point light's
SIGMA = Range(0.0, 1e6, "1/m")  # optical depth 1 over a micrometre
IOR = Range(1.0, 3.0)  # 1: an index-matched boundary (no refraction); diamond is 2.42
WAVE_K = Range(-1e4, 1e4, "rad/m")  # wavelengths down to 0.6 mm
WAVE_PHASE = Range(-1e6, 1e6, "rad")
HG_G = Range(-0.999, 0.999)
WATER_B = Range(0.0, 10.0)  # the 1 + b cos^2 phase of water (0.835 by Morel)
EXPONENT = Range(1.0, 1e5)  # Phong exponent: a lobe of ~1/sqrt(n) rad, 0.2 degrees at 1e5
AIM = Range(0.0, 1.0, hi_open=True)  # the rest of the photons cover the scene
PARALLEL = 0.999  # |cos| between a rectangle's normal and its `up` hint above which it fails
MAX_BASES = 8  # files in one chain of `base`s


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED = _Required()  # the default of a field that must be given


@dataclasses.dataclass(frozen=True)
class Derived:
    """The default of an optional field that is computed from other fields (`text` says
    how)."""

    text: str


# The kinds of value (the loader reads each kind with one `_Ctx` getter).
KINDS = {
    "number": "a number (integer or float)",
    "integer": "an integer",
    "vector": "a list of numbers (its length in the Kind column)",
    "direction": "a list of 3 numbers, not all zero; normalised on load",
    "spectrum": f"a number (every channel) or a list of {CHANNELS} numbers (red, green, blue), "
                "each >= 0",
    "string": "a string",
    "enum": "one of the listed strings",
    "boolean": "true or false",
    "material": "the NAME of a `[materials.NAME]` table",
    "file": "a file name or a non-empty list of file names",
    "table": "a table",
    "named tables": "a table of tables, one per NAME",
    "array of tables": "an array of tables, one `[[...]]` per entry",
    "waves": "an array of `[A, kx, kz, phase]` lists",
}


@dataclasses.dataclass(frozen=True, eq=False)
class Field:
    """One key of a table: its kind, its valid range (numbers: per number, so per component
    of a vector and per channel of a spectrum), default and a one-line description."""

    name: str
    kind: str
    doc: str
    default: Any = REQUIRED
    range: Range | None = None
    unit: str | None = None  # as shown in the page (default: the range's unit)
    n: int = 3  # the length of a vector
    choices: tuple[str, ...] = ()  # enum
    items: tuple[Field, ...] = ()  # the components of each entry (waves)
    nonzero: bool = False  # spectrum: > 0 in some channel
    note: str = ""  # what the range does not say (rules relating it to other fields)

    def __post_init__(self):
        assert self.kind in KINDS, self.kind

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @property
    def shown_unit(self) -> str:
        if self.unit is not None:
            return self.unit
        return self.range.unit if self.range is not None else ""


def _keyed(fields) -> dict:
    return {f.name: f for f in fields}


@dataclasses.dataclass(frozen=True, eq=False)
class Variant:
    """The fields one `type` of a typed table accepts (with the table's common fields)."""

    type: str
    doc: str
    fields: tuple[Field, ...]
    common: tuple[Field, ...] = ()  # set by `Table`
    notes: tuple[str, ...] = ()

    def all_fields(self) -> tuple[Field, ...]:
        return self.common + self.fields

    def __getitem__(self, name: str) -> Field:
        return _keyed(self.all_fields())[name]

    def keys(self) -> set[str]:
        """The keys an entry of this type accepts."""
        return {f.name for f in self.all_fields()}

    def required(self) -> set[str]:
        return {f.name for f in self.all_fields() if f.required}


@dataclasses.dataclass(frozen=True, eq=False)
class Table:
    """A section of the file: `[name]`, `[name.NAME]` or `[[name]]`; typed tables declare
    their common fields (`type` first) and one `Variant` per type."""

    name: str
    kind: str  # "table", "named tables" or "array of tables"
    doc: str
    fields: tuple[Field, ...]
    variants: tuple[Variant, ...] = ()
    default: Any = REQUIRED
    notes: tuple[str, ...] = ()

    def __post_init__(self):
        if self.variants:
            assert self.fields[0].name == "type"
            object.__setattr__(self, "fields", (dataclasses.replace(
                self.fields[0], choices=tuple(v.type for v in self.variants)),)
                + self.fields[1:])
            for v in self.variants:
                object.__setattr__(v, "common", self.fields)

    @property
    def header(self) -> str:
        return {"table": f"[{self.name}]", "named tables": f"[{self.name}.NAME]",
                "array of tables": f"[[{self.name}]]"}[self.kind]

    def __getitem__(self, name: str) -> Field:
        return _keyed(self.fields)[name]

    def variant(self, type_: str) -> Variant:
        return {v.type: v for v in self.variants}[type_]

    def types(self) -> tuple[str, ...]:
        """The `type` choices, in the order error messages list them."""
        return tuple(v.type for v in self.variants)

    def keys(self) -> set[str]:
        """Every key the table accepts (typed: under any of its types)."""
        out = {f.name for f in self.fields}
        for v in self.variants:
            out |= v.keys()
        return out

    def required(self) -> set[str]:
        return {f.name for f in self.fields if f.required}


# ------------------------------------------------------------------ the schema
def _coord(name: str, doc: str, default: Any = REQUIRED, n: int = 3, **kw) -> Field:
    return Field(name, "vector", doc, default, COORD, n=n, **kw)


_SIZE_NOTE = "and >= 1e-6 x the scene's extent"
_CENTER = _coord("center", "The centre.")
_MATERIAL = Field("material", "material", "Its material.")
_RECT = (
    Field("normal", "direction", "The side it faces.", range=DIRECTION),
    Field("size", "vector", "Side lengths [w, h]: w across `up`, h along it.", range=SIZE, n=2,
          note=_SIZE_NOTE),
    Field("up", "direction", "Orients the sides: h runs along its part perpendicular to the "
          "normal.", Derived("y; -z for a normal within 26 degrees of y"), DIRECTION,
          note="not parallel to `normal`"),
)
_RADIUS = Field("radius", "number", "The radius.", range=SIZE, note=_SIZE_NOTE)
_AIM = Field("aim", "number", "The fraction of its photons aimed at the water's footprint "
             "(the caustic caster) instead of the scene's bounding disk.", 0.0, AIM,
             note="> 0 needs `[water]`")
_RADIANCE = Field("radiance", "spectrum", "Emitted radiance.", range=RADIANCE, nonzero=True)
_EMITTER_ALBEDO = Field("albedo", "spectrum", "The diffuse reflectance of its surface.", 0.0,
                        ALBEDO)

BASE = Field("base", "file", "Files read first, in order, this file laid over them "
             "(paths relative to this file).", Derived("none"),
             note=f"at most {MAX_BASES} files in a chain, no cycles")

DOCUMENT = Table("", "table", "The top level of a scene file.", (
    Field("name", "string", "The scene's name (shown in outputs).",
          Derived("the file's name without `.toml`")),
    Field("camera", "table", "The camera: `[camera]`."),
    Field("materials", "named tables", "Named materials: `[materials.NAME]`.", Derived("none")),
    Field("shapes", "array of tables", "Surfaces: `[[shapes]]`.", Derived("none")),
    Field("water", "table", "The water: `[water]`.", Derived("no water")),
    Field("lights", "array of tables", "Lights: `[[lights]]`, at least one."),
))

CAMERA = Table("camera", "table", "A pinhole camera.", (
    _coord("position", "The eye."),
    _coord("target", "The point looked at.", note="not at `position`"),
    Field("up", "direction", "The image's up is its part perpendicular to the view "
          "direction.", [0.0, 1.0, 0.0], DIRECTION,
          note="not parallel to the view direction"),
    Field("fov", "number", "Vertical field of view.", range=FOV),
    Field("width", "integer", "Image width in pixels (`--width` overrides it). Any size in "
          "range renders: a pass too large for the memory runs in chunks; an image whose "
          "film and host buffers exceed the memory is refused before rendering.", range=PIXELS,
          unit="pixels"),
    Field("height", "integer", "Image height in pixels (`--height` overrides it).",
          range=PIXELS, unit="pixels"),
))

MATERIALS = Table("materials", "named tables", "Named materials, used by the shapes' "
                  "`material`, `floor_material` and `wall_material`. NAME is any key.", (
    Field("type", "enum", "The kind of material."),
), variants=(
    Variant("diffuse", "Lambertian.", (
        Field("albedo", "spectrum", "Reflectance.", 0.5, ALBEDO),
    )),
    Variant("mirror", "A perfect specular reflector.", (
        Field("albedo", "spectrum", "Reflectance.", 1.0, ALBEDO),
    )),
    Variant("glass", "A smooth dielectric, lossless (exact Fresnel). A shape's inside is the "
            "side its normal points away from.", (
        Field("ior", "number", "Index of refraction (1: an index-matched boundary, no "
              "refraction).", range=IOR),
    )),
    Variant("glossy", "A Lambertian lobe plus a normalised Phong lobe (SmallVCM's model).", (
        Field("albedo", "spectrum", "The Lambertian reflectance k_d.", 0.0, ALBEDO),
        Field("glossy", "spectrum", "The Phong reflectance k_s.", 0.5, ALBEDO,
              note="albedo + glossy <= 1 in every channel"),
        Field("exponent", "number", "The Phong exponent: a lobe about 1/sqrt(exponent) rad "
              "wide.", 90.0, EXPONENT),
    )),
))

SHAPES = Table("shapes", "array of tables", "Surfaces, each with a material.", (
    Field("type", "enum", "The kind of shape."),
    Field("two_sided", "boolean", "false: scatters only on the side its normal faces, black "
          "from behind (as SmallVCM's and Mitsuba's diffuse).", True,
          note="false: diffuse and glossy materials only"),
), variants=(
    Variant("rect", "A rectangle.", (_CENTER,) + _RECT + (_MATERIAL,)),
    Variant("sphere", "A sphere.", (_CENTER, _RADIUS, _MATERIAL)),
    Variant("basin", "An open box: the floor and four inward-facing walls (five rectangles). "
            "The water's footprint and floor default to its interior.", (
        _coord("min", "[x0, floor, z0]: the floor's corner."),
        _coord("max", "[x1, top, z1]: the opposite corner.", note="above `min` on every axis"),
        Field("floor_material", "material", "The floor's material."),
        Field("wall_material", "material", "The walls' material."),
        _coord("wall_tops", "The walls' tops (y) at x0, x1, z0, z1.", Derived("max[1] each"),
               n=4, note="above the floor"),
    )),
))

_WAVE = (
    Field("A", "number", "amplitude.", range=COORD),
    Field("kx", "number", "wave number along x.", range=WAVE_K),
    Field("kz", "number", "wave number along z.", range=WAVE_K),
    Field("phase", "number", "phase.", range=WAVE_PHASE),
)

WATER = Table("water", "table", "The water: a heightfield surface y = level + sum of A sin(kx x "
              "+ kz z + phase) over the footprint, down to a flat floor, holding a homogeneous "
              "medium. The surface is a smooth dielectric.", (
    Field("level", "number", "The still surface's height (y).", range=COORD),
    Field("waves", "waves", "The surface's sine waves, each `[A, kx, kz, phase]`.", [],
          items=_WAVE),
    Field("sigma_a", "spectrum", "Absorption coefficient.", range=SIGMA),
    Field("sigma_s", "spectrum", "Scattering coefficient.", range=SIGMA),
    Field("phase", "enum", "Phase function: isotropic, Henyey-Greenstein (`g`) or water's "
          "1 + b cos^2.", "isotropic", choices=("isotropic", "hg", "water")),
    Field("g", "number", "Henyey-Greenstein asymmetry (phase = \"hg\").", 0.0, HG_G),
    Field("b", "number", "The b of water's 1 + b cos^2 phase function (phase = \"water\").",
          0.835, WATER_B),
    Field("ior", "number", "Index of refraction.", range=IOR),
    _coord("footprint", "[xmin, xmax, zmin, zmax]: the surface's extent.",
           Derived("the basin's interior"), n=4, note="xmin < xmax, zmin < zmax"),
    Field("floor", "number", "The medium's bottom (y).", Derived("the basin's floor"), COORD,
          note="below the surface's lowest point"),
), default=Derived("no water"))

LIGHTS = Table("lights", "array of tables", "Lights; a scene has at least one.", (
    Field("type", "enum", "The kind of light."),
), variants=(
    Variant("rect", "A rectangle emitting on the side its normal faces.",
            (_CENTER,) + _RECT + (_RADIANCE, _EMITTER_ALBEDO)),
    Variant("sphere", "A sphere emitting outwards from its whole surface.",
            (_CENTER, _RADIUS, _RADIANCE, _EMITTER_ALBEDO)),
    Variant("sun", "A distant light from one direction.", (
        Field("direction", "direction", "The way the light travels.", range=DIRECTION),
        Field("irradiance", "spectrum", "Irradiance on a plane facing the sun.", range=IRRADIANCE,
              unit="W/m^2", nonzero=True),
        dataclasses.replace(_AIM, note="> 0 needs `[water]` and a downward `direction`"),
    )),
    Variant("sky", "Constant radiance from every direction above the horizon (y > 0).",
            (_RADIANCE, _AIM), notes=("at most one sky or background per scene",)),
    Variant("background", "Constant radiance from every direction (SmallVCM's background).",
            (_RADIANCE,), notes=("at most one sky or background per scene",)),
    Variant("point", "An isotropic point light.", (
        _coord("position", "Its position."),
        Field("intensity", "spectrum", "Radiant intensity.", range=INTENSITY, unit="W/sr",
              nonzero=True),
    )),
), notes=(("`aim` (sun, sky): the rest of the photons still start on the scene's bounding "
           "disk, and every technique's MIS uses the mixture's pdf, so the image is unbiased "
           "for any aim; it only moves where the noise is."),))

SECTIONS = (CAMERA, MATERIALS, SHAPES, WATER, LIGHTS)


# ------------------------------------------------------------------ the page
def _num(x: float) -> str:
    """A number for the page: 1e6 rather than 1e+06, 90 rather than 90.0."""
    if float(x).is_integer() and abs(x) < 1e4:
        return str(int(x))
    if x != 0 and not 1e-3 <= abs(x) < 1e4:
        m, e = f"{x:e}".split("e")
        return f"{m.rstrip('0').rstrip('.')}e{int(e)}"
    return f"{x:g}"


def _range_text(f: Field) -> str:
    parts = []
    r = f.range
    if r is not None:
        lo, hi = _num(r.lo), _num(r.hi)
        if f.kind == "integer":
            lo, hi = str(int(r.lo)), str(int(r.hi))
        parts.append(f"{'(' if r.lo_open else '['}{lo}, {hi}{')' if r.hi_open else ']'}")
        if f.kind in ("vector", "direction"):
            parts[-1] += " each"
    if f.kind == "direction":
        parts.append("not all zero")
    if f.kind == "spectrum" and f.nonzero:
        parts.append("> 0 in some channel")
    if f.note:
        parts.append(f.note)
    return "; ".join(parts)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return _num(v)


def _default_text(f: Field) -> str:
    if f.required:
        return "required"
    if isinstance(f.default, Derived):
        return f.default.text
    return f"`{_toml_value(f.default)}`"


def _kind_text(f: Field) -> str:
    if f.kind == "enum":
        return " / ".join(f'`"{c}"`' for c in f.choices)
    if f.kind == "vector":
        return f"vector of {f.n}"
    return f.kind


def _cell(s: str) -> str:
    assert "|" not in s and "\n" not in s, s
    return s


def _field_table(fields, prefix: str = "") -> list[str]:
    rows = ["| Field | Kind | Unit | Valid range | Default | Description |",
            "|---|---|---|---|---|---|"]
    for i, f in enumerate(fields):
        rows.append("| " + " | ".join(_cell(c) for c in (
            f"`{prefix.format(i=i)}`" if prefix else f"`{f.name}`", _kind_text(f),
            f.shown_unit, _range_text(f), _default_text(f),
            f"{f.name}: {f.doc}" if prefix else f.doc)) + " |")
    return rows


_HEADER = re.compile(r'^(\[\[?[A-Za-z0-9_."\- ]+\]\]?)\s*(#.*)?$')


def _blocks(text: str) -> list[tuple[str, str]]:
    """A TOML file's text cut at its table headers: (header, the block's lines)."""
    out, header, lines = [], "", []
    for line in text.splitlines():
        m = _HEADER.match(line)
        if m:
            out.append((header, lines))
            header, lines = m[1], []
        lines.append(line)
    out.append((header, lines))
    blocks = []
    for h, ls in out:
        while ls and (not ls[-1].strip() or ls[-1].lstrip().startswith("#")):
            ls.pop()  # blank lines and the next block's leading comments
        blocks.append((h, "\n".join(ls)))
    return blocks


def _example(scenes: list[tuple[str, str]], table: Table, type_: str | None):
    """The first block of the scene files for `table` (of `type_`): (file, text)."""
    for name, text in scenes:
        for header, block in _blocks(text):
            if table.kind == "named tables":
                match = header.startswith(f"[{table.name}.")
            else:
                match = header == table.header
            typed = type_ is None or re.search(rf'^type\s*=\s*"{type_}"', block, re.MULTILINE)
            if match and typed:
                return name, block
    return None


def _scenes(root: str) -> list[tuple[str, str]]:
    """(relative path, text) of scenes/*.toml and scenes/_base/*.toml: pool.toml, the
    other pools, the rest."""
    d = os.path.join(root, "scenes")
    names = sorted((n for n in os.listdir(d) if n.endswith(".toml")),
                   key=lambda n: (n != "pool.toml", not n.startswith("pool"), n))
    base = os.path.join(d, "_base")
    if os.path.isdir(base):
        names += [f"_base/{n}" for n in sorted(os.listdir(base)) if n.endswith(".toml")]
    out = []
    for n in names:
        with open(os.path.join(d, n), encoding="utf-8") as f:
            out.append((f"scenes/{n}", f.read()))
    return out


def _code(name: str, block: str) -> list[str]:
    return [f"From `{name}`:", "", "```toml", block, "```", ""]


_INTRO = f"""\
# Scene format

<!-- Generated from the schema in jaxvcm/_io/_schema.py by
`python -m jaxvcm._io._scene_format docs/scene-format.md`; do not edit by hand. -->

A scene is one UTF-8 [TOML](https://toml.io) file: `jaxvcm render scene.toml` renders it,
`jaxvcm.load_scene("scene.toml")` loads it as a `Scene`. Lengths are in metres, y is up.
The file must be a regular file of at most {MAX_FILE_BYTES >> 20} MiB (a leading UTF-8
byte-order mark is skipped).
This page is generated from the schema the loader validates against, so every field,
range and default below is the one enforced.

## Kinds of value

| Kind | Written as |
|---|---|
{{kinds}}

## Valid ranges

Every number must be finite and lie in its field's range: each component of a vector,
each channel of a spectrum. The ranges keep every derived value finite in float32, the
renderer's precision: lengths within 1e6 m, so squares and areas stay far below float32's
largest number, and no value is stored as inf. Integers of any size and floats beyond
float64 (inf, nan) are refused the same way, as are unknown keys, missing required fields
and values of the wrong kind. The rules that relate fields (a size against the scene's
extent, a wall top above the floor) follow the range in the Valid range column. Sizes
(rectangle sides, radii, the basin's sides and walls) must also be at least 1e-6 x the
scene's extent (the diagonal of the box around the camera, the shapes, the point lights and
the water): smaller shapes are not resolved in float32.

A file that breaks a rule is refused with one line, `FILE: FIELD: problem`, naming the
merged document's field: `scene.toml: lights[0].radiance: must lie in [0, 1e+15]
W/(m^2 sr), got 1e+39`. Keys that are not bare are shown quoted.

## Shared parts: `base`

A file can name other files under `base` (one name or a list; paths relative to the
file). They are read first, in order, each possibly with its own `base` (at most
{MAX_BASES} files in a chain, no cycles), and the file is laid over them:

- tables merge key by key (`[camera] fov = 20` over a base's camera changes only the fov);
- `[[shapes]]` and `[[lights]]` entries are appended after the bases' ones
  (`shapes[i]` in messages counts the bases' shapes first);
- any other value replaces the base's.

A base need not be a whole scene: `scenes/_base/` holds the Cornell box's parts, and each
Cornell variant is a short file over them.
"""


def format_markdown(root: str | None = None) -> str:
    """The reference page docs/scene-format.md: the format's rules, then one section per
    table with its fields (from the schema above) and examples (from the repository's
    scenes/, pool.toml first). `root`: the repository (default: the one holding this
    package)."""
    if root is None:
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    scenes = _scenes(root)
    kinds = "\n".join(f"| {k} | {_cell(v)} |" for k, v in KINDS.items())
    out = _INTRO.replace("{kinds}", kinds).splitlines()
    out += ["", f"## Complete example: `{scenes[0][0]}`", "", "```toml", scenes[0][1].strip(),
            "```", "", "## Top level", "", DOCUMENT.doc, ""]
    out += _field_table((BASE,) + DOCUMENT.fields) + [""]
    for t in SECTIONS:
        out += [f"## `{t.header}`", "", t.doc, ""]
        if not t.variants:
            out += _field_table(t.fields) + [""]
            for f in t.fields:
                if f.items:
                    out += [f"Each entry of `{f.name}`, `[{', '.join(i.name for i in f.items)}]`:",
                            ""]
                    out += _field_table(f.items, f"{f.name}[j][{{i}}]") + [""]
            ex = _example(scenes, t, None)
            if ex:
                out += _code(*ex)
            continue
        out += _field_table(t.fields) + [""]
        for note in t.notes:
            out += [note, ""]
        for v in t.variants:
            out += [f'### `type = "{v.type}"`', "", v.doc, ""]
            out += _field_table(v.fields) + [""]
            for note in v.notes:
                out += [note[0].upper() + note[1:] + ".", ""]
            ex = _example(scenes, t, v.type)
            if ex:
                out += _code(*ex)
    while out and out[-1] == "":
        out.pop()
    return "\n".join(out) + "\n"


def write_markdown(path: str, root: str | None = None) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(format_markdown(root))
