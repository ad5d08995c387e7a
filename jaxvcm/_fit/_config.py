"""The TOML fit config of `jaxvcm fit CONFIG`: parsing and validation (`load_fit_config`).

Errors are `FitConfigError`s whose str() is one line naming the file and the field.
`WATER_FIELDS` is the one list of the fittable `WaterModel` leaves (spectral mode); their
ranges, and those of the RGB coefficients, are in `_bounds`. Everything a fit would refuse
is refused here, before any scene is rendered: initial values outside the fit's ranges,
targets that cannot be a region's colour (`_colour.target_problem`), a bad max_delta_e.
"""

from __future__ import annotations

import os
import re

import numpy as np

from .._config import ALGORITHMS, MAX_DEPTH, RenderConfig
from .._io._scene_file import SceneError, _Ctx, scene_from_dict
from .._io._schema import IOR, MAX_PIXELS
from .._io._toml import ANY, Range, key_path, read_toml
from .._spectral._scene import MAX_WAVELENGTHS
from .._spectral import spectral_scene
from .._spectral import WaterModel
from ._bounds import SIGMA_FIT, WATER_RANGES, fit_range
from ._colour import SPACES, target_problem
from ._model import Region
from ._solver import MAX_DELTA_E

FREE = ("both", "sigma_a", "sigma_s")  # which coefficients an RGB fit adjusts

CONFIG_DOC = """Fit config (TOML), for `jaxvcm fit CONFIG [--out DIR]`:

  mode = "rgb"                        # rgb (default) | spectral
  space = "srgb"                      # targets' colour space: srgb (linear) | xyz | lab
  [render]    algorithm = "pt", max_depth = 6, rr_depth, radius, passes = 16, seed = 0,
              width, height           (image size of every scene; default: the files')
  [solver]    max_steps = 40, rtol = 1e-4, atol = 1e-5,
              max_delta_e = 2.0       (a region further from its target, in Delta E 2000,
                                       fits badly: `jaxvcm fit` then exits with 4)
              free = "both" | "sigma_a" | "sigma_s"   (RGB only: which coefficients are fitted)
  [init]      sigma_a, sigma_s        (spectra in (1e-9, 1e6) 1/m; default: the first
                                       scene's water)
  [truth]     sigma_a, sigma_s        (optional; only reported: relative errors)
  [scenes.NAME]  file = "scene.toml"  (relative to the config file)
                 override = { ... }   (tables deep-merged into the scene file, e.g.
                                       override.materials.floor.albedo = 0.02)
  [[regions]] name, scene = NAME, rect = [x0, y0, x1, y1] (pixels, half-open, row 0 at
              the top), target = [3 numbers], uncertainty = number | [3 numbers] (optional)
              (targets: > 0 in every component in srgb and xyz; L in (0, 100] in lab)

Spectral mode (mode = "spectral"; jaxvcm.fit_spectral, the scenes upsampled with
jaxvcm.spectral_scene; the water is a jaxvcm.WaterModel, the scenes' RGB sigma_a and
sigma_s are not used):

  params = ["a_cdom", ...]            # fitted WaterModel leaves: a_cdom, S, a_flat, b_p, n_p,
                                      # g, a_w_scale (required)
  linear = ["a_cdom", ...]            # fitted as they are (may cross 0); the others in log
                                      # space (default: none)
  [spectral]  n_wavelengths = 8, ior = "data" | "scene" | number, phase = "auto" | "scene",
              sun = "D65" | "blackbody", sun_temperature = 5778, dispersion = false
  [water]     the model's fixed fields (and the default initial values): a_cdom, S, a_flat,
              b_p, n_p, g, a_w_scale (numbers, in their ranges: jaxvcm/_fit/_bounds.py
              WATER_RANGES), pure_absorption, pure_scattering (booleans); default: pure water
  [init]      NAME = value for names in params (default: [water]'s value; inside the
              range, above 0 in log space)
  [truth]     NAME = value (optional; only reported: errors)
  [solver]    max_steps, rtol, atol, max_delta_e (no free)
"""

WATER_FIELDS = ("a_cdom", "S", "a_flat", "b_p", "n_p", "g", "a_w_scale")  # fittable leaves
WATER_FLAGS = ("pure_absorption", "pure_scattering")
SPECTRAL_KEYS = ("params", "linear", "spectral", "water")  # top-level, spectral mode only


class FitConfigError(ValueError):
    """A malformed fit config. str() is one line: 'FILE: FIELD: problem'."""


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else v
    return out


def _overrides(ov: dict, field: str) -> bool:
    """Whether the override table `ov` sets the scene field `field` ("a.b[2].c") or a table
    or array above it."""
    node = ov
    for part in re.findall(r"[^.\[\]]+|\[\d+\]", field):
        if part.startswith("["):
            i = int(part[1:-1])
            if not isinstance(node, list) or i >= len(node):
                return False
            node = node[i]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            return False
    return True


def load_fit_config(path) -> dict:
    """Parse and validate a fit config -> keyword arguments of `fit` (scenes loaded).
    A spectral config (mode = "spectral") gives the keyword arguments of
    `fit_spectral` plus mode = "spectral" (scenes upsampled to `SpectralScene`s)."""
    src = os.fspath(path)

    class Ctx(_Ctx):
        def fail(self, field, msg):
            raise FitConfigError(f"{self.src}: {field}: {msg}")

    ctx = Ctx(src)
    doc = read_toml(src, FitConfigError)
    if "scenes" not in doc and ("camera" in doc or "lights" in doc):
        raise FitConfigError(f"{src}: a scene file, not a fit config (a fit config names "
                             "its scenes in [scenes.NAME] and its targets in [[regions]])")
    mode = ctx.string(doc.get("mode", "rgb"), "mode", ("rgb", "spectral"))
    spectral = mode == "spectral"
    top = {"mode", "space", "render", "solver", "init", "truth", "scenes", "regions"}
    if not spectral:
        for k in SPECTRAL_KEYS:
            if k in doc:
                ctx.fail(k, 'only in spectral configs (mode = "spectral")')
    else:
        top |= set(SPECTRAL_KEYS)
    ctx.table(doc, top, {"scenes", "regions"} | ({"params"} if spectral else set()), "")
    space = ctx.string(doc.get("space", "srgb"), "space", SPACES)
    r = doc.get("render", {})
    ctx.table(r, {"algorithm", "max_depth", "rr_depth", "radius", "passes", "seed", "width",
                  "height"}, set(), "render")
    cfg = {"algorithm": ctx.string(r.get("algorithm", "pt"), "render.algorithm", ALGORITHMS)}
    for k, hi in (("max_depth", MAX_DEPTH), ("rr_depth", None)):
        if k in r:
            cfg[k] = ctx.integer(r[k], f"render.{k}", hi=hi)
    cfg.setdefault("max_depth", 6)
    if "radius" in r:
        cfg["radius"] = ctx.number(r["radius"], "render.radius", Range(0.0, 1.0, lo_open=True))
    config = RenderConfig(**cfg)
    passes = ctx.integer(r.get("passes", 16), "render.passes")
    seed = ctx.integer(r.get("seed", 0), "render.seed", lo=0, hi=2**32 - 1)
    width = ctx.integer(r["width"], "render.width", hi=MAX_PIXELS) if "width" in r else None
    height = ctx.integer(r["height"], "render.height", hi=MAX_PIXELS) if "height" in r else None
    s = doc.get("solver", {})
    ctx.table(s, {"max_steps", "rtol", "atol", "max_delta_e"}
              | (set() if spectral else {"free"}), set(), "solver")
    free = ctx.string(s.get("free", "both"), "solver.free", FREE)
    max_steps = ctx.integer(s.get("max_steps", 40), "solver.max_steps")
    rtol = ctx.number(s.get("rtol", 1e-4), "solver.rtol", positive=True)
    atol = ctx.number(s.get("atol", 1e-5), "solver.atol", positive=True)
    max_delta_e = ctx.number(s.get("max_delta_e", MAX_DELTA_E), "solver.max_delta_e",
                             positive=True)

    if spectral:
        sp = _spectral_settings(ctx, doc)
    else:
        def spectra(table, field, required, rng=ANY):
            if table is None:
                return None
            ctx.table(table, {"sigma_a", "sigma_s"}, required, field)
            out = {}
            for k in ("sigma_a", "sigma_s"):
                if k in table:
                    v = ctx.spectrum(table[k], f"{field}.{k}", rng)
                    if not np.all(v > 0):
                        ctx.fail(f"{field}.{k}", "must be > 0 in every channel (log-space fit)")
                    out[k] = v
            return out

        init = spectra(doc.get("init"), "init", set(), SIGMA_FIT) or {}  # the fit's range
        truth = spectra(doc.get("truth"), "truth", {"sigma_a", "sigma_s"})

    sc = doc["scenes"]
    if not isinstance(sc, dict) or not sc:
        ctx.fail("scenes", "expected a table of named scenes ([scenes.NAME] file = ...)")
    base = os.path.dirname(os.path.abspath(src))
    scenes = {}
    for name, e in sc.items():
        sf = key_path("scenes", name)
        ctx.table(e, {"file", "override"}, {"file"}, sf)
        f = ctx.string(e["file"], f"{sf}.file")
        fp = f if os.path.isabs(f) else os.path.join(base, f)
        fshow = os.path.relpath(fp) if not os.path.isabs(f) else f
        if not os.path.exists(fp):
            ctx.fail(f"{sf}.file", f"file not found: {fshow}")
        sdoc = read_toml(fshow if not os.path.isabs(f) else fp, FitConfigError)
        ov = e.get("override", {})
        if not isinstance(ov, dict):
            ctx.fail(f"{sf}.override", "expected a table")
        try:
            scene = scene_from_dict(_deep_merge(sdoc, ov), fshow, width=width, height=height)
        except SceneError as err:  # a field the override set: name the override
            field, _, msg = str(err).removeprefix(f"{fshow}: ").partition(": ")
            if not msg or not _overrides(ov, field):
                raise
            ctx.fail(f"{sf}.override.{field}", msg)
        if not scene.water.enabled:
            ctx.fail(sf, "the scene has no water to fit")
        scenes[name] = scene

    regs = doc["regions"]
    if not isinstance(regs, list) or not regs:
        ctx.fail("regions", "expected an array of tables ([[regions]])")
    regions = []
    for i, e in enumerate(regs):
        fld = f"regions[{i}]"
        ctx.table(e, {"name", "scene", "rect", "target", "uncertainty"},
                  {"name", "scene", "rect", "target"}, fld)
        nm = ctx.string(e["name"], f"{fld}.name")
        scn = ctx.string(e["scene"], f"{fld}.scene")
        if scn not in scenes:
            ctx.fail(f"{fld}.scene", f"unknown scene {scn!r} (one of: {', '.join(scenes)})")
        rect = e["rect"]
        if not isinstance(rect, list) or len(rect) != 4:
            ctx.fail(f"{fld}.rect", "expected [x0, y0, x1, y1]")
        rect = [ctx.integer(v, f"{fld}.rect[{j}]", lo=0) for j, v in enumerate(rect)]
        cam = scenes[scn].camera
        if not (rect[0] < rect[2] <= cam.width and rect[1] < rect[3] <= cam.height):
            ctx.fail(f"{fld}.rect", f"{rect} is empty or outside the {cam.width}x{cam.height} "
                                    "image (need x0 < x1 <= width, y0 < y1 <= height)")
        tgt = ctx.vec(e["target"], f"{fld}.target")  # finite numbers
        why = target_problem(tgt, space)
        if why:
            ctx.fail(f"{fld}.target", why)
        unc = None
        if "uncertainty" in e:
            u = e["uncertainty"]
            unc = (ctx.vec(u, f"{fld}.uncertainty") if isinstance(u, list)
                   else np.full(3, ctx.number(u, f"{fld}.uncertainty")))
            if not np.all(unc > 0):
                ctx.fail(f"{fld}.uncertainty", "must be > 0")
            unc = tuple(float(x) for x in unc)
        if any(rg.name == nm for rg in regions):
            ctx.fail(f"{fld}.name", f"duplicate region name {nm!r}")
        regions.append(Region(nm, scn, tuple(rect), tuple(float(x) for x in tgt), unc))
    if not spectral:  # initial values the config leaves to the first scene's water
        w0 = next(iter(scenes.values())).water
        for k in ("sigma_a", "sigma_s"):
            v = np.asarray(getattr(w0, k), np.float64)
            if k not in init and not all(SIGMA_FIT.contains(x) for x in v):
                ctx.fail(f"init.{k}", f"not set, and the first scene's water {k} "
                                      f"{v.tolist()} is outside {SIGMA_FIT.text()}: set "
                                      f"init.{k}")
    if spectral:
        model = WaterModel(**sp["water"])
        try:
            sps = {k: spectral_scene(v, model, **sp["scene_kw"]) for k, v in scenes.items()}
        except ValueError as err:  # pragma: no cover (the settings are validated above)
            ctx.fail("spectral", str(err))
        return dict(mode="spectral", spectral=sps, regions=regions, params=sp["params"],
                    space=space, init=sp["init"], config=config, passes=passes, seed=seed,
                    max_steps=max_steps, rtol=rtol, atol=atol, truth=sp["truth"],
                    linear=sp["linear"], max_delta_e=max_delta_e)
    return dict(scenes=scenes, regions=regions, space=space, config=config, passes=passes,
                seed=seed, init_sigma_a=init.get("sigma_a"), init_sigma_s=init.get("sigma_s"),
                free=free, max_steps=max_steps, rtol=rtol, atol=atol, truth=truth,
                max_delta_e=max_delta_e)


def _spectral_settings(ctx, doc) -> dict:
    """The spectral-only parts of a fit config: params, linear, [spectral], [water], [init],
    [truth] (validated; one-line errors naming the field)."""
    def names(v, field):
        if not isinstance(v, list):
            ctx.fail(field, "expected a list of parameter names")
        out = []
        for j, x in enumerate(v):
            x = ctx.string(x, f"{field}[{j}]", WATER_FIELDS)
            if x in out:
                ctx.fail(f"{field}[{j}]", f"{x!r} listed twice")
            out.append(x)
        return out

    params = names(doc["params"], "params")
    if not params:
        ctx.fail("params", f"nothing to fit (list some of {', '.join(WATER_FIELDS)})")
    linear = names(doc.get("linear", []), "linear")
    for j, x in enumerate(linear):
        if x not in params:
            ctx.fail(f"linear[{j}]", f"{x!r} is not in params")

    spt = doc.get("spectral", {})
    ctx.table(spt, {"n_wavelengths", "ior", "phase", "sun", "sun_temperature", "dispersion"},
              set(), "spectral")
    kw = {"n_wavelengths": ctx.integer(spt.get("n_wavelengths", 8), "spectral.n_wavelengths",
                                       hi=MAX_WAVELENGTHS)}
    ior = spt.get("ior", "data")
    if isinstance(ior, str):
        kw["ior"] = ctx.string(ior, "spectral.ior", ("data", "scene"))
    else:
        kw["ior"] = ctx.number(ior, "spectral.ior", IOR)
    kw["phase"] = ctx.string(spt.get("phase", "auto"), "spectral.phase", ("auto", "scene"))
    kw["sun"] = ctx.string(spt.get("sun", "D65"), "spectral.sun", ("D65", "blackbody"))
    kw["sun_temperature"] = ctx.number(spt.get("sun_temperature", 5778.0),
                                       "spectral.sun_temperature", positive=True)
    disp = spt.get("dispersion", False)
    if not isinstance(disp, bool):
        ctx.fail("spectral.dispersion", f"expected true or false, got {type(disp).__name__}")
    kw["dispersion"] = disp

    wt = doc.get("water", {})
    ctx.table(wt, set(WATER_FIELDS) | set(WATER_FLAGS), set(), "water")
    water = {}
    for k in WATER_FIELDS:
        if k in wt:
            water[k] = ctx.number(wt[k], f"water.{k}", WATER_RANGES[k])
    for k in WATER_FLAGS:
        if k in wt:
            if not isinstance(wt[k], bool):
                ctx.fail(f"water.{k}", f"expected true or false, got {type(wt[k]).__name__}")
            water[k] = wt[k]
    defaults = {"a_cdom": 0.0, "S": 0.015, "a_flat": 0.0, "b_p": 0.0, "n_p": 1.0, "g": 0.9,
                "a_w_scale": 1.0}

    def values(table, field, allowed):
        if table is None:
            return None
        ctx.table(table, set(allowed), set(), field)
        return {k: ctx.number(v, f"{field}.{k}") for k, v in table.items()}

    init = values(doc.get("init"), "init", params) or {}
    for k in params:
        v = init.get(k, water.get(k, defaults[k]))
        if k not in linear and not v > 0:
            ctx.fail(f"init.{k}", f"must be > 0 for a log-space fit, got {v} (set init.{k}, "
                                  "or list it in linear)")
        r = fit_range(k, k in linear)
        if not r.contains(v):
            ctx.fail(f"init.{k}", f"must lie in {r.text()}, got {v:g}"
                                  + ("" if k in init else f" (from [water]; set init.{k})"))
        init[k] = v
    truth = values(doc.get("truth"), "truth", WATER_FIELDS)
    return {"params": params, "linear": linear, "scene_kw": kw, "water": water,
            "init": init, "truth": truth}
