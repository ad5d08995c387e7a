"""`jaxvcm bench`: the speed-vs-error report (docs/benchmarks.md + docs/bench_<scene>.png).
Also `python -m benchmarks.bench ...` from the repository root.

For every (scene, algorithm) the scene is rendered progressively (independent passes
`pass_key(seed, i)`, accumulated in float64 on the host) and the running image is sampled
at fixed wall-time budgets; each sample is compared to a long reference render of the
same scene, size and maximum depth. A second table gives raw throughput at each scene's
full size. Results go into a section of the markdown file delimited by
`<!-- bench:TAG:begin -->` / `<!-- bench:TAG:end -->` (TAG defaults to the algorithms
joined by "-"), so runs of other algorithms or tags keep each other's sections; the
numbers of every section are also kept in a JSON sidecar next to the markdown file
(`benchmarks.json`), from which the per-scene plots (one line per algorithm) are redrawn.

References are stored as EXR + PNG + JSON in the reference directory and reused when the
scene file's sha256, image size, algorithm, configuration and reference seed match and
the stored reference is at least as long as requested (`--rebuild-references` forces a
new one). They use a seed different from the measured renders, so their samples are
independent.

`--compare-mis` (explicit vs recursive MIS seconds per pass) and `--equal-time SEC`
(equal-time image grid) are the vertex-merging modes of `benchmarks/vertex_merging.py`;
`--dispersion` (spectral dispersion modes) is in `benchmarks/spectral.py`.

`--peer mitsuba`: jaxvcm and Mitsuba 3 on the same scenes in one run (camera paths/s of PT
and Mitsuba's `volpath`, equal-time relative RMSE of each against a long jaxvcm VCM
reference, the ratio of image means); `benchmarks/peer_mitsuba.py`. Without Mitsuba it
prints one line and exits with status 2.

`--startup`: cold and warm first pass of `jaxvcm render` in fresh processes, from an empty
and from a warm persistent compilation cache (`benchmarks/startup.py`).

`--smallvcm`: SmallVCM's scene 0 with its settings at 10 / 30 / 90 s against a long VCM
reference, RMSE and paths/s beside SmallVCM's figures (`benchmarks/smallvcm.py`).

`--profile`: seconds per stage of one pass (`jaxvcm.profile_stages`: camera rays, light
emission, subpaths, MIS partials, each technique, merging, film; each stage its own
compiled program) against the whole single-jit pass, one table per scene (stages x
algorithms), median over `--throughput-passes` passes; written into the "Stage profile"
section of `--out` (replaced in place or appended) and `<out stem>_stage-profile.json`.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import re
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxvcm
from jaxvcm import __version__

from . import _common as C
from . import peer_mitsuba as _peer
from . import spectral as _sp
from . import aim_sweep as _as
from . import wide_pool as _wp
from . import smallvcm as _sv
from . import scene_size as _ss
from . import scaling as _sc
from . import startup as _st
from . import vertex_merging as _vm

PROG = "jaxvcm bench"
DEFAULT_SCENES = ("pool.toml", "pool_sun.toml", "pool_sky.toml", "pool_wall.toml")
DEFAULT_BUDGETS = (2.0, 4.0, 8.0, 16.0)
DEFAULT_SIZE = 128
DEFAULT_REFERENCE_TIME = 120.0
QUICK_SIZE = 32
QUICK_BUDGETS = (0.5, 1.0)
QUICK_REFERENCE_TIME = 5.0
THROUGHPUT_DEPTH = 8
TARGET_SCENE = "pool.toml"
TARGET_PATHS_PER_S = 1.5e6  # target: PT, depth 8, pool.toml, 2-core machine
TARGET_CPUS = 2
REF_SEED_OFFSET = 1_000_003  # reference seed = seed + offset: independent samples
MAX_SEED = 2**30
REL_EPS = 0.01  # relMAE denominator offset
PROFILE_DEFAULT_SCENES = ("pool.toml",)
PROFILE_DEFAULT_ALGORITHMS = ("pt", "bdpt", "ppm", "vcm")
PROFILE_DEFAULT_SIZE = 256
PROFILE_TAG = "stage-profile"
# row order of the profile tables (`jaxvcm.profile_stages` names; others go before the sums)
PROFILE_STAGES = ("setup", "camera rays", "light emission", "subpaths",
                  "subpaths, emitter hits, next-event estimation", "mis partials",
                  "glint roots", "emitter hits", "glints", "vertex connection",
                  "manifold next-event estimation", "merging", "film")
_TAG_RE = re.compile(r"^[A-Za-z0-9_.+-]+$")
_SECTION_RE = re.compile(
    r"<!-- bench:(?P<tag>[A-Za-z0-9_.+-]+):begin -->\n?(?P<body>.*?)"
    r"<!-- bench:(?P=tag):end -->\n?", re.S)


# ----------------------------------------------------------------------------- arguments
def render_config(name: str, **kw) -> jaxvcm.RenderConfig:
    """The configuration of an algorithm name of the bench: an algorithm, with suffixes
    "+glints" (the glint technique: `RenderConfig.glints`) and / or "+mnee" (manifold
    next-event estimation: `RenderConfig.manifold_nee`), e.g. "vcm+glints+mnee"."""
    alg, *extra = name.split("+")
    bad = [e for e in extra if e not in ("glints", "mnee")]
    if bad or len(set(extra)) != len(extra):
        raise _Usage(f"unknown algorithm {name!r}: the suffixes are '+glints' and '+mnee'")
    try:
        return jaxvcm.RenderConfig(algorithm=alg, glints="glints" in extra,
                                   manifold_nee="mnee" in extra, **kw)
    except ValueError as e:
        raise _Usage(str(e)) from None


class _Usage(ValueError):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _Usage(message)


def _pos_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {s!r}")
    return v


def _int_ge(lo: int, hi: int | None = None):
    def conv(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        if v < lo or (hi is not None and v >= hi):
            rng = f">= {lo}" if hi is None else f"in [{lo}, {hi})"
            raise argparse.ArgumentTypeError(f"must be {rng}, got {v}")
        return v
    return conv


def _budgets(s: str) -> tuple[float, ...]:
    parts = [p for p in s.replace(" ", "").split(",") if p]
    if not parts:
        raise argparse.ArgumentTypeError("expected comma-separated seconds, e.g. 2,4,8,16")
    return tuple(sorted({_pos_float(p) for p in parts}))


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Speed-vs-error benchmark: renders each (scene, "
                "algorithm) for fixed wall-time budgets, compares to a long reference, "
                "writes a markdown table and log-log plots.")
    p.add_argument("--scenes", nargs="+", metavar="SCENE",
                   help="scene files (default: scenes/pool.toml pool_sun.toml pool_sky.toml "
                   "pool_wall.toml; relative paths are tried from the current directory, "
                   "then from the repository root)")
    p.add_argument("--algorithms", nargs="+", metavar="ALG",
                   help="algorithms, comma or space separated (default: pt)")
    p.add_argument("--budgets", type=_budgets, metavar="SEC,SEC,...",
                   help="wall-time budgets in seconds (default 2,4,8,16)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--size", type=_int_ge(1), metavar="N",
                   help=f"image width = height of the error runs (default {DEFAULT_SIZE})")
    g.add_argument("--full-size", action="store_true",
                   help="use each scene's own image size for the error runs")
    p.add_argument("--max-depth", type=_int_ge(1), default=None, metavar="D",
                   help="maximum path length of the error runs and references (default 8)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--reference-time", type=_pos_float, metavar="SEC",
                   help=f"seconds per reference render (default {DEFAULT_REFERENCE_TIME:g})")
    g.add_argument("--reference-passes", type=_int_ge(2), metavar="N",
                   help="passes per reference render instead of a time")
    p.add_argument("--reference-dir", metavar="DIR",
                   help="where references are stored and reused (default docs/bench_refs/)")
    p.add_argument("--rebuild-references", action="store_true",
                   help="render new references even if matching ones are stored")
    p.add_argument("--reference-algorithm", default=None, metavar="ALG",
                   help="algorithm of the reference renders (default pt; --peer: vcm)")
    p.add_argument("--seed", type=_int_ge(0, MAX_SEED), default=0,
                   help="seed of the measured renders (references use seed + "
                   f"{REF_SEED_OFFSET})")
    p.add_argument("--out", metavar="FILE.md", help="markdown report (default docs/benchmarks.md;"
                   " plots bench_<scene>.png and benchmarks.json go next to it)")
    p.add_argument("--tag", metavar="TAG",
                   help="name of this run's section (default: the algorithms joined by '-')")
    p.add_argument("--throughput-only", action="store_true",
                   help="skip references and errors; measure speed only")
    p.add_argument("--throughput-passes", type=_int_ge(0), default=5, metavar="N",
                   help="timed passes of the full-size throughput rows (default 5; 0: none)")
    p.add_argument("--quick", action="store_true",
                   help=f"tiny run: size {QUICK_SIZE}, budgets "
                   f"{','.join(f'{b:g}' for b in QUICK_BUDGETS)}, reference "
                   f"{QUICK_REFERENCE_TIME:g} s, throughput at the same small size")
    p.add_argument("--quiet", action="store_true", help="no progress messages on stderr")
    g = p.add_argument_group(
        "vertex-merging modes (each writes its own section of --out, replaced in "
        "place or appended, and <out stem>_<mode>.json; --scenes, --algorithms, --size, "
        "--max-depth and --seed apply, --quick only sets size 32, other options are "
        "ignored)")
    m = g.add_mutually_exclusive_group()
    m.add_argument("--compare-mis", action="store_true",
                   help="time mis_form explicit vs recursive per pass, the two interleaved "
                   "pass by pass after warm-up; medians, ratio and max image difference "
                   "(defaults: scenes pool.toml pool_sun.toml, algorithms vcm bdpt, size "
                   f"{_vm.MIS_DEFAULT_SIZE})")
    m.add_argument("--equal-time", type=_pos_float, metavar="SEC",
                   help="render every (scene, algorithm) for SEC wall seconds each (compile "
                   f"excluded); grid PNG {_vm.ET_FIGURE} next to --out and passes, paths/s "
                   "per panel (defaults: scenes pool.toml pool_sun.toml pool_wall.toml, "
                   f"algorithms pt bdpt ppm vcm, size {_vm.ET_DEFAULT_SIZE})")
    m.add_argument("--dispersion", action="store_true",
                   help="spectral dispersion modes off / hero / exact: seconds per pass, "
                   "per-pass noise and efficiency, interleaved after warm-up (defaults: "
                   f"scene pool_sun.toml, algorithm vcm, size {_sp.DEFAULT_SIZE}, "
                   f"{_sp.DEFAULT_ROUNDS} rounds via --mis-pairs)")
    g.add_argument("--mis-pairs", type=_int_ge(1), default=None, metavar="N",
                   help=f"timed pairs of passes of --compare-mis (default "
                   f"{_vm.MIS_DEFAULT_PAIRS}), rounds of --dispersion (default "
                   f"{_sp.DEFAULT_ROUNDS})")
    g = p.add_argument_group(
        "stage profile (writes the 'Stage profile' section of --out, replaced in place or "
        "appended, and <out stem>_stage-profile.json; --scenes, --algorithms, --size, "
        "--full-size, --max-depth, --seed and --throughput-passes apply, --quick only sets "
        "size 32)")
    g.add_argument("--profile", action="store_true",
                   help="median seconds per stage of one pass (each stage compiled on its "
                   "own) and of the whole pass, over --throughput-passes passes (defaults: "
                   f"scene {', '.join(PROFILE_DEFAULT_SCENES)}, algorithms "
                   f"{' '.join(PROFILE_DEFAULT_ALGORITHMS)}, size {PROFILE_DEFAULT_SIZE})")
    g = p.add_argument_group(
        "startup", "cold and warm first pass of `jaxvcm render` in fresh processes "
        "(benchmarks/startup.py)")
    g.add_argument("--startup", action="store_true",
                   help="time `jaxvcm render SCENE --passes 1` from an empty and from a warm "
                        "persistent cache (first scene; default pt bdpt vcm, size 256)")
    g.add_argument("--startup-runs", type=_int_ge(1), default=3, metavar="N",
                   help="runs per algorithm with --startup, each with a fresh cache (3)")
    g.add_argument("--scale-sweep", action="store_true",
                   help="the wide flat sunlit pool at 2, 20, 120 m: vcm and ppm relative "
                        "error against the closed form at equal time, today's emission and "
                        "radius vs aimed where the camera looks (benchmarks/aim_sweep.py)")
    g.add_argument("--sweep-seconds", type=float, default=10.0, metavar="SEC",
                   help="seconds per row of --scale-sweep (10)")
    g.add_argument("--wide-pool", action="store_true",
                   help="the 120 m flat sunlit pool at max depth 10 (floor <-> surface "
                        "interreflection): each algorithm's relative error against the closed "
                        "form at equal time, no aim (default vcm ppm pt+mnee bdpt+mnee "
                        "vcm+mnee; benchmarks/wide_pool.py)")
    g.add_argument("--wide-seconds", type=float, default=60.0, metavar="SEC",
                   help="seconds per algorithm of --wide-pool (60)")
    g.add_argument("--smallvcm", action="store_true",
                   help="SmallVCM's scene 0 (scenes/cornell_sun.toml, 256x256, depth 10, "
                        "its radius and heuristic) at 10 / 30 / 90 s against a long VCM "
                        "reference: RMSE and paths/s beside SmallVCM's figures (default pt "
                        "bdpt ppm bpm vcm; benchmarks/smallvcm.py)")
    g.add_argument("--scene-size", action="store_true",
                   help="compile time, memory and pass time against the number of waves "
                        "(1 to 1000) and lights (1 to 100) (benchmarks/scene_size.py)")
    g.add_argument("--scaling", action="store_true",
                   help="time and memory per pass from 64 k to 4 M paths (chunked), and 1 vs "
                        "2 forced CPU devices (first scene, default vcm, depth 8; "
                        "benchmarks/scaling.py)")
    g = p.add_argument_group(
        "peer renderer (writes the 'Peer: Mitsuba 3' section of --out, replaced in place "
        "or appended, <out stem>_peer-mitsuba.json and peer_mitsuba.png next to it; "
        "--scenes, --size, --max-depth, --seed, --throughput-passes and the reference "
        "options apply; --quick sets size 32, 2 s per renderer, a 5 s reference and the "
        "throughput at size 32; needs the optional extra `peer` (Mitsuba 3): without it, "
        f"one line on stderr and exit status {_peer.EXIT_UNAVAILABLE})")
    g.add_argument("--peer", choices=_peer.PEERS,
                   help="render the same scenes with the peer renderer in the same run: "
                   "camera paths/s of jaxvcm PT and the peer at "
                   f"{_peer.THROUGHPUT_SIZE}x{_peer.THROUGHPUT_SIZE} (first scene) and their "
                   "ratio, then per scene both for --peer-seconds each at --size: relative "
                   "RMSE against a long jaxvcm VCM reference and the ratio of image means "
                   f"(defaults: scenes {' '.join(_peer.DEFAULT_SCENES)}, size "
                   f"{_peer.DEFAULT_SIZE}, reference {_peer.DEFAULT_REFERENCE_TIME:g} s)")
    g.add_argument("--peer-seconds", type=_pos_float, default=None, metavar="SEC",
                   help="equal-time budget per renderer and scene (default "
                   f"{_peer.DEFAULT_SECONDS:g})")
    g.add_argument("--peer-variant", default=_peer.VARIANT, metavar="VARIANT",
                   help=f"Mitsuba variant (default {_peer.VARIANT})")
    return p


# ----------------------------------------------------------------------------- helpers
def repo_root() -> Path:
    """The checkout benchmarks/ lives in (parent of benchmarks/) if it has scenes/,
    otherwise the current directory."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "scenes").is_dir() else Path.cwd()


def _resolve_scene(s: str) -> Path:
    p = Path(s)
    if p.is_file():
        return p
    if not p.is_absolute():
        for base in (repo_root(), repo_root() / "scenes"):
            q = base / p
            if q.is_file():
                return q
    raise FileNotFoundError(f"{s}: scene file not found")


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _split_list(items) -> list[str]:
    out: list[str] = []
    for it in items:
        out += [x for x in it.replace(",", " ").split() if x]
    return out


def _metrics(img: np.ndarray, ref: np.ndarray) -> dict:
    d = img - ref
    rmse = float(np.sqrt(np.mean(d * d)))
    mref = float(np.mean(ref))
    return {
        "rmse": rmse,
        "rel_rmse": rmse / mref if mref > 0 else float("nan"),
        "rel_mae": float(np.mean(np.abs(d) / (np.abs(ref) + REL_EPS))),
    }


def _paths(diag) -> tuple[int, int | None]:
    cam = int(diag.camera_paths)
    lp = getattr(diag, "light_paths", None)
    return cam, (None if lp is None else int(lp))


def _ready(x):
    return jax.block_until_ready(x)


# ----------------------------------------------------------------------------- rendering
def _pass(scene, key, config, index):
    """One pass as `jaxvcm render` does it: the pass index drives the merging radius, and
    a merging overflow re-runs the pass with more room (never a truncated estimate)."""
    img, diag, _ = jaxvcm.render_pass_host(scene, key, config, index)
    return img, diag


def _warm_up(scene, config, seed: int) -> float:
    """Compile (or load from the persistent cache) and run one pass; returns its seconds."""
    t0 = time.perf_counter()
    _ready(_pass(scene, jaxvcm.pass_key(seed, 0), config, 0))
    return time.perf_counter() - t0


def _budget_run(scene, config, seed: int, budgets) -> list[dict]:
    """One progressive render sampled at each budget: for budget B, the image after the
    last pass completed at or before B seconds (the first pass if even that took longer).
    Returns one dict per budget with passes, seconds, path counts and the image."""
    budgets = sorted(budgets)
    out: list[dict] = []
    acc = None
    prev = None  # (passes, seconds, acc, cam, light, nonfinite) after the previous pass
    cam_tot = 0
    light_tot: int | None = None
    nonfinite = 0
    i = 0
    t0 = time.perf_counter()
    while len(out) < len(budgets):
        img, diag = _pass(scene, jaxvcm.pass_key(seed, i), config, i)
        img = np.asarray(_ready(img), dtype=np.float64)
        cam, light = _paths(diag)
        nonfinite += int(diag.nonfinite)
        acc = img if acc is None else acc + img  # new array: `prev` keeps the old one
        i += 1
        t = time.perf_counter() - t0
        cam_tot += cam
        if light is not None:
            light_tot = (light_tot or 0) + light
        cur = (i, t, acc, cam_tot, light_tot, nonfinite)
        while len(out) < len(budgets) and t > budgets[len(out)]:
            snap = prev if prev is not None else cur
            out.append(_budget_row(budgets[len(out)], snap, over=prev is None))
        if len(out) < len(budgets) and t == budgets[len(out)]:
            out.append(_budget_row(budgets[len(out)], cur, over=False))
        prev = cur
    return out


def _budget_row(budget, snap, over: bool) -> dict:
    n, t, acc, cam, light, nonfinite = snap
    return {"budget": budget, "passes": n, "seconds": t, "image": acc / n,
            "camera_paths": cam, "light_paths": light, "nonfinite": nonfinite,
            "over_budget": over}


def _throughput(scene, config, seed: int, passes: int) -> dict:
    """Median wall seconds of `passes` single passes (each waited for; no host copy)."""
    times, cams, lights = [], [], []
    for i in range(passes):
        t0 = time.perf_counter()
        img, diag = _ready(_pass(scene, jaxvcm.pass_key(seed, i), config, i))
        times.append(time.perf_counter() - t0)
        c, lp = _paths(diag)
        cams.append(c)
        lights.append(lp)
    med = float(np.median(times))
    cam = float(np.median(cams))
    row = {"passes": passes, "median_s": med, "min_s": float(min(times)),
           "max_s": float(max(times)), "camera_paths_per_s": cam / med,
           "total_paths_per_s": None}
    if all(lp is not None for lp in lights):
        row["total_paths_per_s"] = (cam + float(np.median(lights))) / med
    return row


# ----------------------------------------------------------------------------- references
def _ref_paths(ref_dir: Path, stem: str, alg: str, w: int, h: int, depth: int):
    base = ref_dir / f"{stem}_{alg}_{w}x{h}_d{depth}"
    return base.with_suffix(".exr"), base.with_suffix(".json")


def _load_reference(exr: Path, side: Path, want: dict, req_passes, req_time, shape,
                    forbidden_seed: int):
    """The stored reference if it matches `want` and is long enough, else None (+ why)."""
    if not (exr.is_file() and side.is_file()):
        return None, "none stored"
    try:
        meta = json.loads(side.read_text())
    except (OSError, ValueError) as e:
        return None, f"unreadable sidecar ({e})"
    for k, v in want.items():
        if meta.get(k) != v:
            return None, f"{k} differs"
    if meta.get("seed") == forbidden_seed:
        return None, "its seed equals the measured renders' seed"
    if req_passes is not None and int(meta.get("passes", 0)) < req_passes:
        return None, f"only {meta.get('passes')} passes < {req_passes}"
    if req_time is not None and float(meta.get("seconds", 0.0)) < 0.95 * req_time:
        return None, f"only {meta.get('seconds')} s < {req_time:g} s"
    try:
        img = jaxvcm.read_exr(str(exr)).astype(np.float64)
    except (OSError, ValueError) as e:
        return None, f"unreadable EXR ({e})"
    if img.shape != shape:
        return None, f"shape {img.shape} != {shape}"
    return (img, meta), "match"


def _render_reference(scene, config, seed: int, req_passes, req_time, log, label) -> tuple:
    """Average passes (float64) for `req_passes` passes or `req_time` seconds (>= 2
    passes), keeping the even and odd passes apart to estimate the reference's noise."""
    acc = [None, None]
    n = [0, 0]
    nonfinite = 0
    t0 = time.perf_counter()
    last = t0
    i = 0
    while True:
        img, diag = _pass(scene, jaxvcm.pass_key(seed, i), config, i)
        img = np.asarray(_ready(img), dtype=np.float64)
        nonfinite += int(diag.nonfinite)
        k = i % 2
        acc[k] = img if acc[k] is None else acc[k] + img
        n[k] += 1
        i += 1
        now = time.perf_counter()
        if now - last > 15:
            log(f"{label}: {i} passes, {now - t0:.0f} s")
            last = now
        if i >= 2 and ((req_passes is not None and i >= req_passes)
                       or (req_time is not None and now - t0 >= req_time)):
            break
    seconds = time.perf_counter() - t0
    ref = (acc[0] + acc[1]) / i
    a, b = acc[0] / n[0], acc[1] / n[1]
    # Var(a - b) = s^2 (1/n0 + 1/n1), Var(ref) = s^2 / N, per pixel.
    noise = float(np.sqrt(np.mean((a - b) ** 2) * (1.0 / i) / (1.0 / n[0] + 1.0 / n[1])))
    return ref, {"passes": i, "seconds": round(seconds, 3), "noise_rmse": noise,
                 "nonfinite": nonfinite}


def _get_reference(a, scene_path: Path, scene, stem: str, sha: str, log, config=None) -> tuple:
    """The run's reference of `scene`: stored and matching, else rendered and stored.
    `config`: the reference's configuration (default: `a.reference_algorithm` at
    `a.max_depth`)."""
    given = config is not None
    if not given:
        config = render_config(a.reference_algorithm, max_depth=a.max_depth)
    w, h = scene.camera.width, scene.camera.height
    ref_seed = a.seed + REF_SEED_OFFSET
    name = config.algorithm if given else a.reference_algorithm.replace("+", "-")
    exr, side = _ref_paths(a.reference_dir, stem, name, w, h, config.max_depth)
    want = {"scene_sha256": sha, "width": w, "height": h, "algorithm": config.algorithm,
            "max_depth": config.max_depth, "config": dataclasses.asdict(config)}
    shape = (h, w, 3)
    label = f"reference {stem} {w}x{h} {config.algorithm} d{config.max_depth}"
    if not a.rebuild_references:
        got, why = _load_reference(exr, side, want, a.reference_passes, a.reference_time,
                                   shape, a.seed)
        if got is not None:
            img, meta = got
            log(f"{label}: reused {exr} ({meta['passes']} passes, {meta['seconds']} s)")
            return img, meta, True
        log(f"{label}: rendering ({why}; "
            + (f"{a.reference_passes} passes" if a.reference_passes
               else f"{a.reference_time:g} s") + ")")
    else:
        log(f"{label}: rendering (--rebuild-references)")
    _warm_up(scene, config, ref_seed)
    img, info = _render_reference(scene, config, ref_seed, a.reference_passes,
                                  a.reference_time, log, label)
    mean = float(np.mean(img))
    meta = dict(want)
    meta.update({
        "scene": str(scene_path), "scene_name": scene.name, "seed": ref_seed,
        "request": ({"passes": a.reference_passes} if a.reference_passes
                    else {"seconds": a.reference_time}),
        **info, "noise_rel_rmse": info["noise_rmse"] / mean if mean > 0 else None,
        "mean": mean, "version": __version__, "date": C.now(),
    })
    a.reference_dir.mkdir(parents=True, exist_ok=True)
    jaxvcm.write_outputs(str(exr), img.astype(np.float32), meta)
    log(f"{label}: {info['passes']} passes in {info['seconds']} s -> {exr}")
    # use exactly what later runs will read back (float32)
    return img.astype(np.float32).astype(np.float64), meta, False


# ----------------------------------------------------------------------------- report
def _fmt_rate(x) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:,.0f}"


def _fmt_g(x, digits=4) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}g}"


HEADER = """\
# jaxvcm benchmarks: speed vs error

The tables on this page are generated by `jaxvcm bench` (`benchmarks/bench.py`, run from the
source checkout). Each run writes its own section between the HTML-comment markers
`bench:TAG:begin` and `bench:TAG:end` (TAG: the algorithms, `--tag`, or the mode) and
leaves the rest of the file as it is: the few lines of reading after each section are
written by hand and survive a re-run. The numbers of every section are also kept in JSON
beside this file (`{json}` and `benchmarks_<mode>.json`), from which the plots
`bench_<scene>.png` are drawn. A section's first line names the machine, the software and
the time of its run; sections are re-run one at a time, so they may describe different
builds of the renderer. The renderer's current speed is summarised in
[Performance](design/performance.md).

## Methodology

- **Error runs.** Each (scene, algorithm) is rendered progressively at the run's image size
  and maximum depth, with independent passes (keys `pass_key(seed, i)`) accumulated in
  float64 on the host, as `jaxvcm render` does; one warm-up pass (the compilation) runs
  before the clock starts. The running image is sampled at each time budget B: a row shows
  the image after the last pass that completed within B seconds, so the rows of one run are
  correlated. Rows marked `*` took longer than the budget for even one pass.
- **Rates.** passes/s = passes / seconds; camera paths/s = passes x W x H x spp / seconds;
  total paths/s counts the light paths too, for the algorithms that trace them.
- **References.** A long render per (scene, size, max depth) with the run's reference
  algorithm and the seed + {off}, so that its samples are independent of the measured
  ones; stored as EXR with a JSON record and reused while scene, size, algorithm and
  configuration match.
- **Errors** over all pixels and channels: RMSE; **relRMSE = RMSE / mean(reference)**;
  relMAE = mean(|img - ref| / (ref + {eps})). The reference is itself noisy: its own RMSE,
  estimated from its even and odd passes, is given as *ref. noise*; measured MSE is about
  the true MSE plus ref. noise squared, so errors near that floor say little. A reference
  lacks what its algorithm cannot sample (a BDPT reference misses the sun's caustics seen
  through the water surface), and a merging algorithm's radius bias shows as an error
  floor.
- **Throughput.** At each scene's full size (`--quick`: the small size) and max depth
  {depth}: the median wall seconds per pass over the timed passes, each waited for, after a
  warm-up pass (no host copy, no accumulation); camera paths/s = W x H x spp / median. The
  target line compares path tracing on `scenes/{tscene}` with {target:.1f} M camera
  paths/s on a {tcpu}-core machine.
- Timings are wall clock on a machine that may be shared with other processes: compare
  rows of one run rather than runs.

## Machine (latest run)

{machine}

"""


def _section(tag: str, res: dict) -> str:
    m = res["machine"]
    L = [f"## Run `{tag}`", "",
         f"- {C.machine_line(m)}",
         f"- command: `{res['command']}`",
         f"- algorithms: {', '.join(res['algorithms'])}; seed {res['seed']}"]
    if res["throughput_only"]:
        L.append("- throughput only (no references, no errors)")
    else:
        L.append(f"- error runs: size {res['size_desc']}, max depth {res['max_depth']}, "
                 f"budgets {', '.join(f'{b:g}' for b in res['budgets'])} s; references: "
                 f"{res['reference_algorithm']}, {res['reference_request']}")
    L.append("")
    rows = res["rows"]
    if rows:
        has_light = any(r.get("light_paths") is not None for r in rows)
        L += ["### Passes within the budgets" if res["throughput_only"] else "### Error vs time",
              ""]
        cols = ["scene", "algorithm", "size", "budget s", "passes", "seconds", "passes/s",
                "camera paths/s"]
        if has_light:
            cols.append("total paths/s")
        if not res["throughput_only"]:
            cols += ["RMSE", "relRMSE", "relMAE", "ref. noise (rel)"]
        L += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in rows:
            s = r["seconds"]
            cells = [r["scene"], r["algorithm"], f"{r['width']}x{r['height']}",
                     f"{r['budget']:g}", f"{r['passes']}{'*' if r['over_budget'] else ''}",
                     f"{s:.3f}", f"{r['passes'] / s:.3g}", _fmt_rate(r["camera_paths"] / s)]
            if has_light:
                lp = r.get("light_paths")
                cells.append(_fmt_rate((r["camera_paths"] + lp) / s) if lp is not None
                             else "–")
            if not res["throughput_only"]:
                cells += [_fmt_g(r.get("rmse")), _fmt_g(r.get("rel_rmse")),
                          _fmt_g(r.get("rel_mae")), _fmt_g(r.get("ref_noise_rel"), 3)]
            L.append("| " + " | ".join(cells) + " |")
        L.append("")
        if any(r["nonfinite"] for r in rows):
            L += ["**Warning:** some passes produced non-finite contributions (zeroed): "
                  + ", ".join(f"{r['scene']}/{r['algorithm']}: {r['nonfinite']}"
                              for r in rows if r["nonfinite"]), ""]
    refs = res.get("references") or {}
    if refs:
        L += ["References:", ""]
        for stem, r in refs.items():
            L.append(f"- {stem}: {r['algorithm']}, {r['width']}x{r['height']}, max depth "
                     f"{r['max_depth']}, {r['passes']} passes in {r['seconds']} s (seed "
                     f"{r['seed']}), mean {_fmt_g(r.get('mean'))}, noise RMSE "
                     f"{_fmt_g(r.get('noise_rmse'))} (rel {_fmt_g(r.get('noise_rel_rmse'), 3)})"
                     f"{'' if r.get('reused') else ' (rendered in this run)'}")
        L.append("")
    tp = res["throughput"]
    if tp:
        has_light = any(r.get("total_paths_per_s") is not None for r in tp)
        L += ["### Throughput", ""]
        cols = ["scene", "algorithm", "size", "max depth", "timed passes", "median s/pass",
                "min s", "max s", "camera paths/s"]
        if has_light:
            cols.append("total paths/s")
        L += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in tp:
            cells = [r["scene"], r["algorithm"], f"{r['width']}x{r['height']}",
                     str(r["max_depth"]), str(r["passes"]), f"{r['median_s']:.4g}",
                     f"{r['min_s']:.4g}", f"{r['max_s']:.4g}",
                     _fmt_rate(r["camera_paths_per_s"])]
            if has_light:
                cells.append(_fmt_rate(r.get("total_paths_per_s")))
            L.append("| " + " | ".join(cells) + " |")
        L.append("")
    L += [_target_text(res), ""]
    stems = sorted({r["scene"] for r in rows if r.get("rel_rmse") is not None})
    for stem in stems:
        L += [f"![{stem}: relative RMSE vs seconds](bench_{stem}.png)", ""]
    return "\n".join(L)


def _target_text(res: dict) -> str:
    m = res["machine"]
    tstem = Path(TARGET_SCENE).stem
    hit = [r for r in res["throughput"] if r["scene"] == tstem and r["algorithm"] == "pt"
           and r["max_depth"] == THROUGHPUT_DEPTH and r["full_size"]]
    head = (f"**Target** (path tracing, max depth {THROUGHPUT_DEPTH}, `scenes/{TARGET_SCENE}` "
            f"at full size, >= {TARGET_PATHS_PER_S / 1e6:.1f} M camera paths/s on a "
            f"{TARGET_CPUS}-core machine): ")
    if not hit:
        return head + "not measured in this run (needs pt on scenes/pool.toml and full-size " \
                      "throughput rows)."
    r = hit[0]
    x = r["camera_paths_per_s"]
    ratio = x / TARGET_PATHS_PER_S
    verdict = "met" if ratio >= 1 else f"NOT met ({1 / ratio:.3g}x too slow)"
    cpu = m["cpu_count"]
    note = "" if cpu == TARGET_CPUS else (f" Note: this machine has {cpu} CPUs, not "
                                          f"{TARGET_CPUS}.")
    return (head + f"measured {x / 1e6:.4g} M camera paths/s at {r['width']}x{r['height']} "
            f"= {ratio:.3g} x the target: {verdict}.{note}")


def _merge_markdown(old: str, header: str, tag: str, body: str) -> str:
    """`old` with its generated header (everything before the first section marker, when
    it is the generated one) regenerated and `tag`'s section replaced in place or appended;
    all other text, hand-written sections between or after the markers included, is kept."""
    block = f"<!-- bench:{tag}:begin -->\n{body.rstrip()}\n<!-- bench:{tag}:end -->\n"
    if not old.strip():
        return header + "\n" + block
    first = _SECTION_RE.search(old)
    head_end = first.start() if first else len(old)
    rest = old[head_end:]
    if old.startswith(header.split("\n", 1)[0]):  # our generated header: regenerate it
        old = header + "\n" + rest
    mine = [m for m in _SECTION_RE.finditer(old) if m.group("tag") == tag]
    if mine:
        m = mine[0]
        return old[:m.start()] + block + old[m.end():]
    return old.rstrip("\n") + "\n\n" + block


def _plot(path: Path, stem: str, all_results: dict) -> bool:
    """relRMSE vs seconds, log-log, one line per (tag, algorithm) that has errors for `stem`."""
    from matplotlib.figure import Figure  # slow import, only when plotting

    lines = []
    floors = []
    for tag, res in all_results.items():
        by_alg: dict[str, list] = {}
        for r in res.get("rows", []):
            if (r["scene"] == stem and r.get("rel_rmse") is not None
                    and math.isfinite(r["rel_rmse"]) and r["rel_rmse"] > 0):
                by_alg.setdefault(r["algorithm"], []).append(r)
        for alg, rs in by_alg.items():
            rs.sort(key=lambda r: r["seconds"])
            lines.append((alg, tag, rs))
            if rs[0].get("ref_noise_rel"):
                floors.append(rs[0]["ref_noise_rel"])
    if not lines:
        return False
    algs = [a for a, _, _ in lines]
    fig = Figure(figsize=(6.0, 4.2), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    for alg, tag, rs in lines:
        label = alg if algs.count(alg) == 1 else f"{alg} [{tag}]"
        w, h = rs[0]["width"], rs[0]["height"]
        ax.loglog([r["seconds"] for r in rs], [r["rel_rmse"] for r in rs], "o-",
                  label=f"{label} ({w}x{h})")
    alg, tag, rs = lines[0]
    t0, e0 = rs[0]["seconds"], rs[0]["rel_rmse"]
    ts = np.array([t0, max(r["seconds"] for _, _, q in lines for r in q)])
    if ts[1] > ts[0]:
        ax.loglog(ts, e0 * np.sqrt(t0 / ts), ":", color="gray", label="∝ 1/sqrt(t)")
    if floors:
        ax.axhline(min(floors), color="gray", ls="--", lw=0.8, label="reference noise")
    ax.set_xlabel("wall seconds (compile excluded)")
    ax.set_ylabel("relative RMSE (RMSE / mean(ref))")
    ax.set_title(f"{stem}: error vs time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with jaxvcm.atomic_path(str(path)) as tmp:
        fig.savefig(tmp, format="png")
    return True


def _publish(out: Path, tag: str, res: dict, log) -> None:
    """Update the markdown section, the JSON sidecar and the plots of `res`'s scenes."""
    out.parent.mkdir(parents=True, exist_ok=True)
    side = out.with_suffix(".json")
    try:
        allres = json.loads(C.read_text(side) or "{}")
        if not isinstance(allres, dict):
            allres = {}
    except ValueError:
        allres = {}
    allres[tag] = res
    C.write_json(side, allres)
    header = HEADER.format(json=side.name, off=REF_SEED_OFFSET, eps=REL_EPS,
                           depth=THROUGHPUT_DEPTH, tscene=TARGET_SCENE,
                           target=TARGET_PATHS_PER_S / 1e6, tcpu=TARGET_CPUS,
                           machine="- " + C.machine_line(res["machine"]))
    C.write_text(out, _merge_markdown(C.read_text(out), header, tag, _section(tag, res)))
    for stem in sorted({r["scene"] for r in res["rows"]}):
        png = out.parent / f"bench_{stem}.png"
        if _plot(png, stem, allres):
            log(f"plot -> {png}")


# ----------------------------------------------------------------------------- stage profile
def run_profile(a, argv, log) -> dict:
    """`jaxvcm.profile_stages` for every (scene, algorithm); the markdown section and the
    JSON sidecar; prints the section."""
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "max_depth": a.max_depth, "passes": a.throughput_passes, "seed": a.seed,
           "algorithms": a.algorithms, "scenes": []}
    for path in a.scene_paths:
        size = {} if a.full_size else {"width": a.size, "height": a.size}
        scene = jaxvcm.load_scene(path, **size)
        w, h = scene.camera.width, scene.camera.height
        row = {"scene": path.stem, "width": w, "height": h, "seconds": {}}
        for alg in a.algorithms:
            cfg = render_config(alg, max_depth=a.max_depth)
            log(f"profile: {path.stem} {alg} {w}x{h} d{a.max_depth}: compiling every stage, "
                f"then {a.throughput_passes} passes")
            t0 = time.perf_counter()
            prof = jaxvcm.profile_stages(scene, cfg, passes=a.throughput_passes, seed=a.seed)
            row["seconds"][alg] = prof
            log(f"  {time.perf_counter() - t0:.1f} s in all; whole pass "
                f"{prof['whole pass']:.4f} s")
        res["scenes"].append(row)
    body = profile_markdown(res, C.machine_line(res["machine"]))
    C.upsert_section(a.out, PROFILE_TAG, body)
    C.write_json(a.out.with_name(f"{a.out.stem}_{PROFILE_TAG}.json"), res)
    print(body)
    log(f"report -> {a.out}")
    return res


def _stage_rows(per_alg: dict) -> list[str]:
    names = list(dict.fromkeys(n for prof in per_alg.values() for n in prof
                               if n != "whole pass"))
    rank = {n: i for i, n in enumerate(PROFILE_STAGES)}
    return sorted(names, key=lambda n: rank.get(n, len(rank)))


def profile_markdown(res: dict, machine_line: str) -> str:
    algs = res["algorithms"]
    L = ["## Stage profile", "",
         f"- {machine_line}",
         f"- command: `{res['command']}`",
         f"- max depth {res['max_depth']}, seed {res['seed']}; median wall seconds over "
         f"{res['passes']} passes (keys `pass_key(seed, i)`) of `jaxvcm.profile_stages`: "
         "each stage of the pass (`integrate`'s) jitted on its own, its inputs "
         "computed by the earlier stages and waited for before its clock starts, every "
         "program compiled and run once before timing. *whole pass*: the usual single-jit "
         "pass on the same keys. Separate programs cannot fuse across stages, so their sum "
         "is usually more than the whole pass. `subpaths` is the trace (camera and light "
         "subpaths in one trace when both run) with the records' start vertices; PT "
         "evaluates its emitter hits and next-event estimation inside its trace (one "
         "stage, no records: `_inline`); `merging` "
         "is the hash-grid build plus the gather (ppm: photon gather); `–`: the algorithm "
         "has no such stage.", ""]
    for row in res["scenes"]:
        per = row["seconds"]
        L += [f"### {row['scene']}, {row['width']}x{row['height']}", "",
              "| stage | " + " | ".join(algs) + " |", "|---|" + "---|" * len(algs)]
        for name in _stage_rows(per):
            L.append(f"| {name} | " + " | ".join(
                f"{per[a][name]:.4f}" if name in per[a] else "–" for a in algs) + " |")
        sums = [sum(v for n, v in per[a].items() if n != "whole pass") for a in algs]
        L.append("| sum of stages | " + " | ".join(f"{x:.4f}" for x in sums) + " |")
        L.append("| **whole pass** | " + " | ".join(
            f"**{per[a]['whole pass']:.4f}**" for a in algs) + " |")
        L.append("")
    return "\n".join(L)


# ----------------------------------------------------------------------------- main
def _settings(argv):
    a = _parser().parse_args(argv)
    a.mode = ("compare-mis" if a.compare_mis else "equal-time" if a.equal_time
              else "dispersion" if a.dispersion else None)
    if a.profile:
        if a.mode:
            raise _Usage(f"--profile: not allowed with --{a.mode}")
        a.mode = "profile"
        if a.throughput_passes < 1:
            raise _Usage("--throughput-passes: --profile needs at least 1")
    if a.startup:
        if a.mode:
            raise _Usage(f"--startup: not allowed with --{a.mode}")
        a.mode = "startup"
    if a.scale_sweep:
        if a.mode:
            raise _Usage(f"--scale-sweep: not allowed with --{a.mode}")
        a.mode = "scale-sweep"
    if a.wide_pool:
        if a.mode:
            raise _Usage(f"--wide-pool: not allowed with --{a.mode}")
        a.mode = "wide-pool"
    if a.smallvcm:
        if a.mode:
            raise _Usage(f"--smallvcm: not allowed with --{a.mode}")
        a.mode = "smallvcm"
    if a.scene_size:
        if a.mode:
            raise _Usage(f"--scene-size: not allowed with --{a.mode}")
        a.mode = "scene-size"
    if a.scaling:
        if a.mode:
            raise _Usage(f"--scaling: not allowed with --{a.mode}")
        a.mode = "scaling"
    if a.peer:
        if a.mode:
            raise _Usage(f"--peer: not allowed with --{a.mode}")
        a.mode = "peer"
        if a.algorithms:
            raise _Usage("--algorithms: not available with --peer (jaxvcm runs pt, the "
                         "reference vcm)")
    elif a.peer_seconds is not None:
        raise _Usage("--peer-seconds: only with --peer")
    if a.peer_seconds is None:
        a.peer_seconds = 2.0 if a.quick else _peer.DEFAULT_SECONDS
    if a.reference_algorithm is None:
        a.reference_algorithm = _peer.REFERENCE_ALGORITHM if a.mode == "peer" else "pt"
    if a.mis_pairs is None:
        a.mis_pairs = _sp.DEFAULT_ROUNDS if a.mode == "dispersion" else _vm.MIS_DEFAULT_PAIRS
    if a.mode not in (None, "profile") and a.full_size:
        raise _Usage(f"--full-size: not available with --{a.mode}")
    if a.mode and a.throughput_only:
        raise _Usage(f"--throughput-only: not available with --{a.mode}")
    mode_algs = {"compare-mis": _vm.MIS_DEFAULT_ALGORITHMS,
                 "equal-time": _vm.ET_DEFAULT_ALGORITHMS,
                 "dispersion": list(_sp.DEFAULT_ALGORITHMS),
                 "profile": list(PROFILE_DEFAULT_ALGORITHMS),
                 "startup": list(_st.DEFAULT_ALGORITHMS),
                 "scaling": ["vcm"],
                 "scene-size": ["vcm"],
                 "scale-sweep": ["vcm", "ppm"],
                 "wide-pool": list(_wp.DEFAULT_ALGORITHMS),
                 "smallvcm": list(_sv.DEFAULT_ALGORITHMS),
                 "peer": ["pt"]}.get(a.mode, ["pt"])
    a.algorithms = _split_list(a.algorithms or mode_algs)
    for alg in a.algorithms + [a.reference_algorithm]:
        if alg.partition("+")[0] not in jaxvcm.ALGORITHMS:
            raise _Usage(f"unknown algorithm {alg!r}; one of {', '.join(jaxvcm.ALGORITHMS)}"
                         f" (with '+glints', '+mnee': the glint technique, manifold NEE)")
        render_config(alg)
    a.algorithms = list(dict.fromkeys(a.algorithms))
    root = repo_root()
    mode_scenes = {"compare-mis": _vm.MIS_DEFAULT_SCENES,
                   "equal-time": _vm.ET_DEFAULT_SCENES,
                   "dispersion": _sp.DEFAULT_SCENES,
                   "profile": PROFILE_DEFAULT_SCENES,
                   "startup": PROFILE_DEFAULT_SCENES,
                   "scaling": PROFILE_DEFAULT_SCENES,
                   "scene-size": PROFILE_DEFAULT_SCENES,
                   "peer": _peer.DEFAULT_SCENES}.get(a.mode, DEFAULT_SCENES)
    names = _split_list(a.scenes) if a.scenes else [str(Path("scenes") / s)
                                                     for s in mode_scenes]
    a.scene_paths = [_resolve_scene(s) for s in names]
    stems = [p.stem for p in a.scene_paths]
    if len(set(stems)) != len(stems):
        raise _Usage(f"--scenes: scene file names must be distinct, got {', '.join(stems)}")
    if a.budgets is None:
        a.budgets = QUICK_BUDGETS if a.quick else DEFAULT_BUDGETS
    if a.size is None and not a.full_size:
        a.size = (QUICK_SIZE if a.quick else
                  {"compare-mis": _vm.MIS_DEFAULT_SIZE,
                   "equal-time": _vm.ET_DEFAULT_SIZE,
                   "dispersion": _sp.DEFAULT_SIZE,
                   "profile": PROFILE_DEFAULT_SIZE,
                   "startup": PROFILE_DEFAULT_SIZE,
                   "peer": _peer.DEFAULT_SIZE}.get(a.mode, DEFAULT_SIZE))
    if a.max_depth is None:
        a.max_depth = 8
    if a.reference_time is None and a.reference_passes is None:
        a.reference_time = (QUICK_REFERENCE_TIME if a.quick else
                            _peer.DEFAULT_REFERENCE_TIME if a.mode == "peer"
                            else _sv.DEFAULT_REFERENCE_TIME if a.mode == "smallvcm"
                            else DEFAULT_REFERENCE_TIME)
    a.reference_dir = Path(a.reference_dir) if a.reference_dir else root / "docs" / "bench_refs"
    a.out = Path(a.out) if a.out else root / "docs" / "benchmarks.md"
    if a.out.suffix.lower() != ".md":
        raise _Usage(f"--out: must end in .md, got {str(a.out)!r}")
    a.tag = a.tag or "-".join(a.algorithms)
    if not _TAG_RE.match(a.tag):
        raise _Usage(f"--tag: only letters, digits and _.+- allowed, got {a.tag!r}")
    return a


def run(a, argv) -> dict:
    """Run the benchmark described by the parsed settings `a`; returns the results."""
    log = C.Log(a.quiet)
    res = {
        "machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
        "algorithms": a.algorithms, "seed": a.seed, "throughput_only": a.throughput_only,
        "size_desc": "scene's own" if a.full_size else f"{a.size}x{a.size}",
        "max_depth": a.max_depth, "budgets": list(a.budgets),
        "reference_algorithm": a.reference_algorithm,
        "reference_request": (f"{a.reference_passes} passes" if a.reference_passes
                              else f"{a.reference_time:g} s"),
        "rows": [], "throughput": [], "references": {},
    }
    for path in a.scene_paths:
        stem = path.stem
        sha = _sha256(path)
        size = {} if a.full_size else {"width": a.size, "height": a.size}
        scene = jaxvcm.load_scene(path, **size)
        w, h = scene.camera.width, scene.camera.height
        ref = None
        if not a.throughput_only:
            ref, meta, reused = _get_reference(a, path, scene, stem, sha, log)
            res["references"][stem] = {**{k: meta.get(k) for k in (
                "algorithm", "width", "height", "max_depth", "passes", "seconds", "seed",
                "noise_rmse", "noise_rel_rmse", "mean")}, "reused": reused}
        for alg in a.algorithms:
            config = render_config(alg, max_depth=a.max_depth)
            tw = _warm_up(scene, config, a.seed)
            log(f"{stem} {alg} {w}x{h} d{a.max_depth}: warm-up {tw:.2f} s; timing "
                f"{max(a.budgets):g} s")
            for r in _budget_run(scene, config, a.seed, a.budgets):
                img = r.pop("image")
                row = {"scene": stem, "algorithm": alg, "width": w, "height": h,
                       "max_depth": a.max_depth, "spp": config.spp, **r}
                if ref is not None:
                    row.update(_metrics(img, ref))
                    row["ref_noise_rel"] = res["references"][stem]["noise_rel_rmse"]
                res["rows"].append(row)
                log(f"  {r['budget']:g} s: {r['passes']} passes in {r['seconds']:.2f} s"
                    + (f", relRMSE {row['rel_rmse']:.4g}" if ref is not None else ""))
        if a.throughput_passes > 0:
            tsize = size if a.quick else {}
            tscene = jaxvcm.load_scene(path, **tsize)
            tw_, th_ = tscene.camera.width, tscene.camera.height
            for alg in a.algorithms:
                config = render_config(alg, max_depth=THROUGHPUT_DEPTH)
                _warm_up(tscene, config, a.seed)
                r = _throughput(tscene, config, a.seed, a.throughput_passes)
                res["throughput"].append({
                    "scene": stem, "algorithm": alg, "width": tw_, "height": th_,
                    "max_depth": THROUGHPUT_DEPTH, "full_size": not tsize, **r})
                log(f"{stem} {alg} throughput {tw_}x{th_} d{THROUGHPUT_DEPTH}: median "
                    f"{r['median_s']:.3f} s/pass, {r['camera_paths_per_s']:,.0f} camera paths/s")
        _publish(a.out, a.tag, res, log)  # after every scene: an interrupted run keeps some
    log(f"report -> {a.out}")
    return res


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        a = _settings(argv)
    except SystemExit as e:  # --help
        return e.code if isinstance(e.code, int) else 0
    except (ValueError, OSError) as e:
        print(f"jaxvcm: error: bench: {' '.join(str(e).split())}", file=sys.stderr, flush=True)
        return 2
    jaxvcm.enable_compilation_cache()  # leaves an already configured cache alone
    try:
        if a.mode == "compare-mis":
            _vm.run_compare_mis(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "equal-time":
            _vm.run_equal_time(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "dispersion":
            _sp.run_dispersion(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "profile":
            run_profile(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "startup":
            _st.run_startup(a, argv, a.scene_paths[0], C.Log(a.quiet))
            return 0
        if a.mode == "scale-sweep":
            _as.run_sweep(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "wide-pool":
            _wp.run_wide(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "smallvcm":
            _sv.run_smallvcm(a, argv, C.Log(a.quiet))
            return 0
        if a.mode == "scene-size":
            _ss.run_scene_size(a, argv, a.scene_paths[0], C.Log(a.quiet))
            return 0
        if a.mode == "scaling":
            _sc.run_scaling(a, argv, a.scene_paths[0], C.Log(a.quiet))
            return 0
        if a.mode == "peer":
            log = C.Log(a.quiet)
            return _peer.run_peer(a, argv, log, lambda a_, path, scene: _get_reference(
                a_, path, scene, path.stem, _sha256(path), log))
        res = run(a, argv)
    except (ValueError, OSError) as e:  # e.g. a malformed scene file: one line, status 2
        print(f"jaxvcm: error: bench: {' '.join(str(e).split())}", file=sys.stderr, flush=True)
        return 2
    if not a.quiet:
        print(_target_text(res))
    print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
