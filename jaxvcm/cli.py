"""Command line: `jaxvcm render | info | export | bench | fit`.

Errors in the scene file or the arguments are reported as ONE line on stderr,
`jaxvcm: error: <message>`, with exit status 2 and no traceback. An interrupted render
(Ctrl-C: SIGINT, or SIGTERM) finishes its pass in flight, writes the image set of the
passes it has and exits with 130 (SIGINT) or 143 (SIGTERM); a second signal stops it at
once, still writing what it has (`jaxvcm._signals`).
A render's warnings (non-finite contributions zeroed, a black image) are one line each,
`jaxvcm: warning: <message>`, and are also in the JSON sidecar ("warnings"). A render in
which every path contribution was non-finite writes its (black) outputs and exits with 3.
A fit that did not converge, or converged but fits badly (a region further than the
config's max_delta_e from its target) or with a coefficient at a bound of its range,
writes its outputs (fit.json says "converged" and "problems"), prints its verdict as one
line `jaxvcm: warning: <verdict>` and exits with 4.

Exit statuses: 0 done; 2 bad input (arguments, scene or fit config; nothing run);
3 a render whose every contribution was non-finite; 4 a fit that failed (above);
130 / 143 interrupted by SIGINT / SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import jaxvcm

from . import _fit, _hosts, _io, _signals
from ._host_memory import reuse_host_buffers as _reuse_host_buffers
from ._compilation_cache import enable_compilation_cache as _enable_compilation_cache
from ._config import ALGORITHMS, MAX_DEPTH, MAX_RADIUS, RenderConfig
from ._devices import resolve_devices
from ._memory import parse_bytes
from ._fit import WATER_FIELDS
from ._fit._bounds import WATER_RANGES
from ._io import FORMATS, check_writable, export_scene
from ._io._schema import MAX_PIXELS
from ._render import ALL_NONFINITE
from ._scene import (LIGHT_NAMES, LIGHT_POINT, LIGHT_RECT, LIGHT_SPHERE, LIGHT_SUN, MAT_NAMES,
                     PHASE_NAMES)
from ._spectral import WaterModel
from ._spectral._scene import MAX_WAVELENGTHS

PROG = "jaxvcm"


class _UsageError(Exception):
    """An argparse error, reported as one line."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of usage + message, same exit status
        raise _UsageError(message)


def _err(msg) -> int:
    msg = str(msg).split("\n--------------------\n")[0]  # without JAX's traceback note
    msg = " ".join(msg.split()) or "unknown error"
    print(f"{PROG}: error: {msg}", file=sys.stderr, flush=True)
    return 2


EXIT_ALL_NONFINITE = 3
EXIT_FIT_FAILED = 4


def _report_render(out: str) -> int:
    """Print the warnings recorded in the render's JSON sidecar; the exit status (0, or
    EXIT_ALL_NONFINITE when every contribution was non-finite)."""
    with open(os.path.splitext(out)[0] + ".json", encoding="utf-8") as f:
        warns = json.load(f).get("warnings", [])
    for w in warns:
        print(f"{PROG}: warning: {w}", file=sys.stderr, flush=True)
    return EXIT_ALL_NONFINITE if any(ALL_NONFINITE in w for w in warns) else 0


def _finite_float(positive=False):
    def conv(s):
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be finite, got {s!r}")
        if positive and not v > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {s!r}")
        return v
    return conv


def _short(s: str) -> str:
    return repr(s) if len(s) <= 24 else repr(s[:20] + "...") + f" ({len(s)} characters)"


def _finite_float_in(lo, hi):
    def conv(s):
        v = _finite_float()(s)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must lie in [{lo:g}, {hi:g}], got {_short(s)}")
        return v
    return conv


def _pos_int(lo=1, hi=None):
    def conv(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {_short(s)}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {_short(s)}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi}, got {_short(s)}")
        return v
    return conv


def _parser() -> argparse.ArgumentParser:

    p = _Parser(prog=PROG, description="Differentiable JAX renderer for analytic water scenes.")
    p.add_argument("--version", action="version", version=f"{PROG} {jaxvcm.__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    r = sub.add_parser("render", help="render a scene progressively to EXR + PNG + JSON")
    r.add_argument("scene", metavar="SCENE", help="scene file (.toml)")
    r.add_argument("--algorithm", default="vcm", choices=ALGORITHMS,
                   help="vcm (default): all connections and merges; pt, lt, bdpt, ppm, bpm: "
                        "subsets of the same core")
    r.add_argument("--glints", action=argparse.BooleanOptionalAction, default=None,
                   help="the glint technique: the lights seen in the waves, by a Newton "
                        "solve on the water surface per pixel (default: on for pt, bdpt, bpm "
                        "and vcm)")
    r.add_argument("--manifold-nee", action=argparse.BooleanOptionalAction, default=False,
                   help="manifold next-event estimation: the light reaching vertices under "
                        "the water through the surface, by a Newton solve per vertex (pt, "
                        "bdpt, bpm, vcm; off by default: on the default pool it lowers the "
                        "typical pixel's error but costs 1.8x per pass, docs/benchmarks.md)")
    r.add_argument("--radius", type=_finite_float_in(1e-9, MAX_RADIUS), default=None,
                   metavar="R", help="first-pass merging radius as a fraction of the scene's "
                                     "view radius, the size of what the camera sees "
                                     "(ppm/bpm/vcm; default 0.005)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--passes", type=_pos_int(), metavar="N",
                   help="number of passes (1 sample per pixel each)")
    g.add_argument("--time", type=_finite_float(positive=True), metavar="SEC",
                   help="render for this many seconds after the first pass, which includes "
                        "the compilation (default: 60 if --passes is not given)")
    r.add_argument("--seed", type=_pos_int(lo=0, hi=2**32 - 1), default=0)
    r.add_argument("--width", type=_pos_int(hi=MAX_PIXELS), metavar="W")
    r.add_argument("--height", type=_pos_int(hi=MAX_PIXELS), metavar="H")
    r.add_argument("--out", metavar="FILE.exr",
                   help="output EXR (PNG and JSON go next to it); default out/<scene>.exr")
    r.add_argument("--snapshot-every", type=_finite_float(positive=True),
                   metavar="SEC", help="write atomic snapshots every SEC seconds")
    r.add_argument("--exposure", type=_finite_float_in(-64.0, 64.0), default=0.0, metavar="EV",
                   help="exposure of the PNG preview, in stops")
    r.add_argument("--max-depth", type=_pos_int(hi=MAX_DEPTH), metavar="D",
                   help="maximum path length in segments")
    r.add_argument("--devices", type=_pos_int(), default=None, metavar="N",
                   help="run N passes at once, one on each of the first N local devices "
                        "(default: all local devices; the image does not depend on N)")
    r.add_argument("--memory", default=None, metavar="SIZE",
                   help="working memory per pass, e.g. 4G: each pass is traced in as many "
                        "chunks of paths as keep it under SIZE (measured by compiling two "
                        "probe chunks); default: the device's memory, on the CPU the "
                        "host's available memory")
    r.add_argument("--resume", action="store_true",
                   help="continue the render in --out (same scene, seed, algorithm and "
                        "settings) up to --passes in all, or for --time more seconds")
    r.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="multi-process render on jax.distributed: process 0's address "
                        "(default: $JAX_COORDINATOR_ADDRESS); every process renders its "
                        "share of the passes, process 0 writes the outputs")
    r.add_argument("--num-processes", type=_pos_int(hi=4096), default=None, metavar="P",
                   help="processes of a multi-process render (default: $JAX_NUM_PROCESSES)")
    r.add_argument("--process-id", type=_pos_int(lo=0, hi=4095), default=None, metavar="I",
                   help="this process's id, 0..P-1 (default: $JAX_PROCESS_ID)")
    r.add_argument("--techniques", action="store_true",
                   help="also write every technique's image as a layer of the EXR, keyed "
                        "by path length k and technique (kK_sS_tT: the connection of s light "
                        "and t camera vertices; kK_merge_sS_tT: photon y_(s-1) merged at "
                        "z_(t-1)); their sum is the image; one device, one chunk")
    r.add_argument("--aim-view", action="store_true",
                   help="before rendering, a pilot pass of camera paths aims the scene's "
                        "aimed lights ([[lights]] aim) at the water where the camera looks "
                        "and sets the first-pass merging radius from the pixel footprint "
                        "(overrides --radius; jaxvcm.aim_at_view)")
    r.add_argument("--quiet", action="store_true", help="no progress line")
    r.add_argument("--spectral", action="store_true",
                   help="spectral mode (hero wavelengths, CIE XYZ film; jaxvcm.render_spectral): "
                        "the water is a WaterModel (pure water unless --water), the scene's "
                        "RGB sigma_a / sigma_s are not used; --passes N (default 16), no --time, "
                        "no --snapshot-every")
    r.add_argument("--wavelengths", type=_pos_int(hi=MAX_WAVELENGTHS), default=None, metavar="C",
                   help="wavelengths per pass with --spectral (default 8)")
    r.add_argument("--water", default=None, metavar="K=V[,K=V]",
                   help="WaterModel fields with --spectral, e.g. a_cdom=0.05,b_p=0.1 "
                        "(a_cdom, S, a_flat, b_p, n_p, g, a_w_scale)")

    i = sub.add_parser("info", help="describe a scene")
    i.add_argument("scene", metavar="SCENE")

    e = sub.add_parser("export", help="tessellate a scene to a mesh file (.glb, .ply, .obj)")
    e.add_argument("scene", metavar="SCENE")
    e.add_argument("out", metavar="OUT", help="OUT.glb, OUT.ply or OUT.obj")

    f = sub.add_parser("fit", help="fit water coefficients to target colours (fit.json + "
                       "fit.png); RGB or spectral (mode = \"spectral\"); config format: "
                       "jaxvcm/_fit/_config.py CONFIG_DOC")
    f.add_argument("config", metavar="CONFIG", help="fit config (.toml)")
    f.add_argument("--out", metavar="DIR", help="output directory (default out/<config>)")
    f.add_argument("--quiet", action="store_true", help="no per-step lines")

    sub.add_parser("bench", help="benchmarks, from a source checkout (arguments are passed to "
                   "benchmarks/bench.py; `jaxvcm bench --help`)", add_help=False)
    return p


def _default_out(scene_path: str) -> str:
    stem = os.path.splitext(os.path.basename(scene_path))[0] or "render"
    return os.path.join("out", stem + ".exr")


def _water_model(text: str | None):
    """--water 'a_cdom=0.05,b_p=0.1' -> WaterModel (pure water for None)."""
    kw = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        k, eq, v = item.partition("=")
        k = k.strip()
        if not eq or k not in WATER_FIELDS:
            raise ValueError(f"--water: expected KEY=VALUE with KEY one of "
                             f"{', '.join(WATER_FIELDS)}, got {item.strip()!r}")
        try:
            x = float(v)
        except ValueError:
            raise ValueError(f"--water: {k}: expected a number, got {v.strip()!r}") from None
        if not math.isfinite(x) or not WATER_RANGES[k].contains(x):
            raise ValueError(f"--water: {k}: must lie in {WATER_RANGES[k].text()}, got {x:g}")
        kw[k] = x
    return WaterModel(**kw)


def _cmd_render_spectral(a, out, config) -> int:


    if a.time is not None:
        raise ValueError("--time: not available with --spectral; use --passes N")
    if a.snapshot_every is not None:
        raise ValueError("--snapshot-every: not available with --spectral")
    for flag, v in (("--devices", a.devices), ("--resume", a.resume or None),
                    ("--memory", a.memory),
                    ("--coordinator", a.coordinator), ("--num-processes", a.num_processes),
                    ("--process-id", a.process_id)):
        if v is not None:
            raise ValueError(f"{flag}: not available with --spectral (one device)")
    water = _water_model(a.water)
    passes = a.passes or 16
    scene = jaxvcm.load_scene(a.scene, width=a.width, height=a.height)
    sp = jaxvcm.spectral_scene(scene, water, n_wavelengths=a.wavelengths or 8)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    check_writable(out)
    _enable_compilation_cache()
    t0 = time.perf_counter()
    try:
        with _quiet_nonfinite_warning():
            jaxvcm.render_spectral(sp, passes=passes, seed=a.seed, config=config, out=out,
                                   exposure=a.exposure)
    except KeyboardInterrupt as e:
        return _interrupted(e, out)
    if not a.quiet:
        print(f"spectral: {passes} passes x {sp.n_wavelengths} wavelengths in "
              f"{time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    print(out)
    return _report_render(out)


@contextlib.contextmanager
def _quiet_nonfinite_warning():
    """The library's non-finite warning silenced: the CLI prints it as one line itself."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*non-finite path contributions")
        yield


def _interrupted(e: KeyboardInterrupt, out: str | None) -> int:
    """One line for a render stopped by SIGINT / SIGTERM (`_signals`); its exit status
    (130 / 143). The render has written the set of the passes it had."""
    n = getattr(e, "passes", 0)
    what = f" ({e})" if isinstance(e, _signals.Interrupted) else ""
    kept = (f" after {n} pass{'es' if n != 1 else ''}: {out}" if n and out
            and os.path.exists(out) else " before its first pass: nothing written"
            if not n else "")
    print(f"{PROG}: interrupted{what}{kept}", file=sys.stderr, flush=True)
    return getattr(e, "status", 130)


def _cmd_render(a) -> int:

    out = _default_out(a.scene) if a.out is None else a.out
    if not out.strip():
        raise ValueError("--out: empty; name an .exr file")
    if os.path.splitext(out)[1].lower() != ".exr":
        raise ValueError(f"--out: must end in .exr, got {out!r}")
    _io.check_output_set(out)  # before anything is loaded, compiled or rendered
    if not a.spectral and (a.wavelengths is not None or a.water is not None):
        raise ValueError(("--wavelengths" if a.wavelengths is not None else "--water")
                         + ": only with --spectral")
    passes, tlimit = a.passes, a.time
    if passes is None and tlimit is None:
        tlimit = 60.0
    cfg = {"algorithm": a.algorithm}
    cfg["glints"] = (a.glints if a.glints is not None
                     else a.algorithm in ("pt", "bdpt", "bpm", "vcm"))
    cfg["manifold_nee"] = a.manifold_nee
    if a.max_depth is not None:
        cfg["max_depth"] = a.max_depth
    if a.radius is not None:
        cfg["radius"] = a.radius
    config = RenderConfig(**cfg)
    if a.techniques:
        for flag, v in (("--spectral", a.spectral or None), ("--resume", a.resume or None),
                        ("--memory", a.memory), ("--coordinator", a.coordinator),
                        ("--num-processes", a.num_processes), ("--process-id", a.process_id)):
            if v is not None:
                raise ValueError(f"{flag}: not available with --techniques (one device, "
                                 f"one chunk, one process)")
        if a.devices is not None and a.devices > 1:
            raise ValueError("--devices: --techniques runs on one device")
    if a.spectral:
        return _cmd_render_spectral(a, out, config)
    if _hosts.requested(a.coordinator, a.num_processes, a.process_id):
        _hosts.initialize(a.coordinator, a.num_processes, a.process_id)  # before any backend
    resolve_devices(a.devices)  # before anything is loaded or written
    if a.memory is not None:
        parse_bytes(a.memory)
    scene = jaxvcm.load_scene(a.scene, width=a.width, height=a.height)
    if a.aim_view:
        if not any(x > 0 for x in scene.lights.aim):
            raise ValueError("--aim-view: the scene has no aimed light (set [[lights]] aim)")
        scene, config, guide = jaxvcm.aim_at_view(scene, config)
        if not a.quiet:
            x0, x1, z0, z1 = guide.aim_rect
            print(f"{PROG}: aimed at {x1 - x0:.3g} m x {z1 - z0:.3g} m of the water "
                  f"({guide.under_water} of {guide.paths} pilot paths under it); radius "
                  f"{config.radius:.3g} of the view radius ({guide.footprint:.3g} m "
                  f"pixel footprint)", file=sys.stderr)
    lead = _hosts.is_lead()
    if lead:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        check_writable(out)
    _enable_compilation_cache()
    try:
        with _quiet_nonfinite_warning():
            jaxvcm.render(scene, algorithm=a.algorithm, passes=passes, time=tlimit,
                          seed=a.seed, snapshot_every=a.snapshot_every, out=out,
                          exposure=a.exposure, scene_path=a.scene, config=config,
                          progress=not a.quiet, devices=a.devices, resume=a.resume,
                          memory=a.memory, techniques=a.techniques)
    except KeyboardInterrupt as e:
        return _interrupted(e, out)
    if not lead:
        return 0
    print(out)
    return _report_render(out)


def _fmt_vec(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v, dtype=np.float64).ravel()) + "]"


def describe(scene) -> str:
    """A human-readable summary of a loaded scene."""
    cam = scene.camera
    fov = math.degrees(2 * math.atan(float(cam.tan_half_fov)))
    lines = [
        f"name:      {scene.name}",
        f"image:     {cam.width} x {cam.height}, {scene.channels} channels",
        f"camera:    position {_fmt_vec(cam.origin)}, forward {_fmt_vec(cam.forward)}, "
        f"fov {fov:.4g} deg (vertical)",
    ]
    rl = np.asarray(scene.rects.light)
    sl = np.asarray(scene.spheres.light)
    lines.append(f"rects:     {scene.rects.count} ({int(np.sum(rl >= 0))} emissive)")
    lines.append(f"spheres:   {scene.spheres.count} ({int(np.sum(sl >= 0))} emissive)")
    one = scene.materials.one_sided or (False,) * len(scene.materials.kind)
    kinds = [MAT_NAMES.get(k, str(k)) + (" one-sided" if o else "")
             for k, o in zip(scene.materials.kind, one)]
    lines.append(f"materials: {len(kinds)} ({', '.join(kinds)})")
    w = scene.water
    if w.enabled:
        waves = np.stack([np.asarray(x, np.float64) for x in (w.amp, w.kx, w.kz, w.phase0)], 1)
        phase = PHASE_NAMES.get(w.phase_kind, str(w.phase_kind))
        if phase == "hg":
            phase += f" (g = {float(w.g):.4g})"
        elif phase == "water":
            phase += f" (b = {float(w.b):.4g})"
        lines += [
            f"water:     level {float(w.level):.4g}, {waves.shape[0]} waves, "
            f"ior {float(w.ior):.4g}, phase {phase}",
            f"           sigma_a {_fmt_vec(w.sigma_a)} 1/m, sigma_s {_fmt_vec(w.sigma_s)} 1/m",
            f"           footprint x [{float(w.footprint[0]):.4g}, {float(w.footprint[1]):.4g}]"
            f", z [{float(w.footprint[2]):.4g}, {float(w.footprint[3]):.4g}], "
            f"floor {float(w.floor):.4g}",
        ]
        for j, (A, kx, kz, ph) in enumerate(waves):
            lines.append(f"           wave {j}: A {A:.4g}, k ({kx:.4g}, {kz:.4g}), "
                         f"phase {ph:.4g}")
    else:
        lines.append("water:     none")
    L = scene.lights
    lines.append(f"lights:    {L.count}")
    rad = np.asarray(L.radiance, np.float64)
    for j, (k, sh) in enumerate(zip(L.kind, L.shape)):
        name = LIGHT_NAMES.get(k, str(k))
        what = ("irradiance" if k == LIGHT_SUN else "intensity" if k == LIGHT_POINT
                else "radiance")
        extra = ""
        if k == LIGHT_RECT:
            p0 = np.asarray(scene.rects.p0[sh], np.float64)
            e1 = np.asarray(scene.rects.e1[sh], np.float64)
            e2 = np.asarray(scene.rects.e2[sh], np.float64)
            n = np.cross(e1, e2)
            extra = (f", center {_fmt_vec(p0 + 0.5 * (e1 + e2))}, area "
                     f"{np.linalg.norm(n):.4g} m^2, normal {_fmt_vec(n / np.linalg.norm(n))}")
        elif k == LIGHT_SPHERE:
            extra = (f", center {_fmt_vec(scene.spheres.center[sh])}, radius "
                     f"{float(scene.spheres.radius[sh]):.4g}")
        elif k == LIGHT_SUN:
            extra = f", direction {_fmt_vec(L.direction[j])}"
        elif k == LIGHT_POINT:
            extra = f", position {_fmt_vec(L.position[j])}"
        lines.append(f"  light {j}: {name}, {what} {_fmt_vec(rad[j])}{extra}")
    b = np.asarray(scene.bounds, np.float64)
    lines.append(f"bounds:    {_fmt_vec(b[0])} .. {_fmt_vec(b[1])}")
    lines.append(f"view:      radius {float(scene.view_radius):.4g} m (the merging radius's "
                 f"reference length)")
    return "\n".join(lines)


def _cmd_info(a) -> int:

    print(describe(jaxvcm.load_scene(a.scene)))
    return 0


def _cmd_export(a) -> int:

    ext = os.path.splitext(a.out)[1].lower()
    if ext not in FORMATS:  # fail before loading the scene
        raise ValueError(f"export: unknown format {ext or '(none)'!r} of {a.out!r}; "
                         f"use one of {', '.join(FORMATS)}")
    scene = jaxvcm.load_scene(a.scene)
    d = os.path.dirname(os.path.abspath(a.out))
    if not os.path.isdir(d):
        raise FileNotFoundError(f"{a.out}: directory {d} does not exist")
    check_writable(a.out)
    export_scene(scene, a.out)
    print(a.out)
    return 0


def _cmd_fit(a) -> int:

    kw = _fit.load_fit_config(a.config)  # validate everything before any rendering
    out = (os.path.join("out", os.path.splitext(os.path.basename(a.config))[0] or "fit")
           if a.out is None else a.out)
    if not out.strip():
        raise ValueError("--out: empty; name the folder for the fit's outputs")
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"--out: {out!r} exists and is not a directory")
    try:  # writable before the fit, not after it
        os.makedirs(out, exist_ok=True)
        check_writable(os.path.join(out, "fit.json"))
    except OSError as e:
        raise ValueError(f"--out: {out!r}: cannot write there ({e.strerror or e})") from None
    _enable_compilation_cache()
    if kw.pop("mode", "rgb") == "spectral":
        res = _fit.fit_spectral(**kw, progress=not a.quiet)
        jp, pp = _fit.write_outputs_spectral(res, out)
    else:
        res = _fit.fit(**kw, progress=not a.quiet)
        jp, pp = _fit.write_outputs(res, out)
    print(res.summary())
    print(jp)
    print(pp)
    if res.problems:
        print(f"{PROG}: warning: {res.verdict}", file=sys.stderr, flush=True)
        return EXIT_FIT_FAILED
    return 0


def _benchmarks_dir() -> Path:
    """Where `jaxvcm bench` looks for the benchmarks: <checkout>/benchmarks/, beside this
    package's directory <checkout>/jaxvcm/ (a monkeypatch point for tests)."""
    return Path(__file__).resolve().parent.parent / "benchmarks"


def _import_benchmarks():
    """The `benchmarks` package of the source checkout, or a one-line reason it is missing.

    This is the ONE place where the library reaches the benchmarks. They are deliberately
    not part of the installed package (pyproject installs jaxvcm* only) and the library
    never imports them otherwise: `benchmarks/` is a top-level directory of the source
    checkout, beside `jaxvcm/`. With the README's editable install (`pip install -e .`),
    `jaxvcm` is imported from the checkout, so `benchmarks/` is found next to it; a regular
    (non-editable, wheel) install has no such directory and `jaxvcm bench` fails with one
    line. The package is loaded from that exact directory by file location rather than by
    putting the checkout on sys.path, so an unrelated `benchmarks` package elsewhere on
    sys.path (or in the current directory) is never picked up and sys.path is left alone.
    If `benchmarks` is already imported from that directory (e.g. `python -m
    benchmarks.bench`, or pytest run from the checkout) that module is reused."""
    pkg = _benchmarks_dir()
    init = pkg / "__init__.py"
    if not init.is_file():
        return None, (f"bench: the benchmarks are not installed with the package; run it from "
                      f"a source checkout installed with `pip install -e .` (no {pkg})")
    mod = sys.modules.get("benchmarks")
    if mod is None:
        spec = importlib.util.spec_from_file_location(
            "benchmarks", init, submodule_search_locations=[str(pkg)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules["benchmarks"] = mod
        try:
            spec.loader.exec_module(mod)
        except BaseException:
            del sys.modules["benchmarks"]
            raise
    elif Path(getattr(mod, "__file__", None) or "").resolve() != init.resolve():
        return None, (f"bench: another package named 'benchmarks' is already imported "
                      f"({getattr(mod, '__file__', None)}), not {init}")
    return importlib.import_module("benchmarks.bench"), None


def _cmd_bench(rest: list[str]) -> int:
    bench, why = _import_benchmarks()
    if bench is None:
        return _err(why)
    _enable_compilation_cache()
    rc = bench.main(rest)
    return int(rc) if rc is not None else 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "bench":
            return _cmd_bench(argv[1:])
        a = _parser().parse_args(argv)
        if a.command == "render":
            with _signals.handled():
                return _cmd_render(a)
        if a.command == "info":
            return _cmd_info(a)
        if a.command == "export":
            return _cmd_export(a)
        if a.command == "fit":
            with _signals.handled():
                return _cmd_fit(a)
        return _err(f"unknown command {a.command!r}")  # pragma: no cover
    except _UsageError as e:
        return _err(e)
    except (ValueError, OSError) as e:  # SceneError is a ValueError
        return _err(e)
    except KeyboardInterrupt as e:
        print(f"{PROG}: interrupted" + (f" ({e})" if isinstance(e, _signals.Interrupted)
                                        else ""), file=sys.stderr, flush=True)
        return getattr(e, "status", 130)
    except SystemExit as e:  # --help
        return e.code if isinstance(e.code, int) else (0 if e.code is None else _err(e.code))


def entry() -> None:
    """Process entry point (console script, `python -m jaxvcm`, `python -m jaxvcm.cli`).
    After an interrupt (status 130 or 143) the outputs are already complete on disk, so the
    process leaves at once instead of tearing down the interpreter: a SIGINT that lands
    while XLA worker threads are busy (a pass in flight, a compilation) could otherwise
    keep the process alive for as long as they take. `render` and `bench` run with the
    passes' host buffers reused (`_host_memory`: set before the runtime's threads start)."""
    if sys.argv[1:2] in (["render"], ["bench"]):
        _reuse_host_buffers()
    rc = main()
    if rc in (130, 143):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":
    entry()
