"""`jaxvcm bench --peer mitsuba`: jaxvcm and Mitsuba 3 on the same pool, in the same run.

The jaxvcm scene (`jaxvcm.load_scene`) is rebuilt as a Mitsuba 3 scene dict:

- camera: `perspective`, the same origin, view direction and up, the vertical field of
  view (`fov_axis = "y"`), the same size, a box pixel filter (jaxvcm jitters uniformly
  inside each pixel and averages);
- rectangles (basin floor and walls, area lights) as `rectangle` shapes whose `to_world`
  maps [-1, 1]^2 onto p0 + u e1 + v e2 with normal e1 x e2. jaxvcm's diffuse surfaces
  shade both sides and Mitsuba's `diffuse` is one-sided (black from behind), so every
  diffuse BSDF is wrapped in `twosided`, which matches ours exactly (the outer faces of the
  basin walls are seen by the camera and lit by the sky);
- the water surface: `jaxvcm.water_grid` (the heightfield tessellated to an N x N vertex
  grid, default 128, with the exact analytic vertex normals) as a triangle mesh with a
  smooth `dielectric` (int_ior = the water's IOR, ext_ior = 1) and the water as its
  `interior` medium: `homogeneous`, sigma_t = sigma_a + sigma_s, albedo = sigma_s /
  sigma_t, `isotropic` phase (`hg` with the same g when the scene uses it). The basin's
  floor and walls below the surface are not medium boundaries in either renderer: a path
  that enters the water stays in it until it leaves through the surface;
- lights: a rect light is an `area` emitter (one-sided, on the side of its normal) on its
  rectangle, with the rectangle's own (black by default) diffuse reflectance; the sky
  (radiance L for directions with y > 0, nothing below) is an `envmap` of a lat-long
  bitmap with L in its upper half and 0 in its lower half (bilinear lookup: the horizon is
  blurred over one row, 180 / rows degrees); a sun is a `directional` emitter with the same
  irradiance; a sphere light is an `area` emitter on a `sphere` (Mitsuba's emits outwards
  only, jaxvcm's both ways).
- integrator: `volpath`, the same max depth (both count path segments), Russian roulette
  from the same depth (Mitsuba's roulette probability differs from jaxvcm's: same
  expectation, different noise).

Measured, in one run (every figure a median after a warm-up render, so compilation is
excluded): camera paths/s of jaxvcm PT and of Mitsuba at the throughput size (256x256) and
their ratio; then, per scene, each renderer for the same wall-clock budget at the error
size, the relative RMSE of each image against one long jaxvcm VCM reference (stored and
reused like the other bench references), and the ratio of the image means of jaxvcm PT and
Mitsuba with its standard error (from the per-pass means). On `pool_sky.toml`, where both
renderers converge quickly and no caustic path is involved, the mean ratio is a
correctness cross-check of the two implementations.

Without Mitsuba (or without a working LLVM backend for it) the bench prints one line and
exits with status 2 (`EXIT_UNAVAILABLE`): nothing was measured. The scene-dict builder
(`scene_spec`) is plain Python and NumPy; only `to_mitsuba` and the renders need Mitsuba.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

import jaxvcm

from . import _common as C

PEERS = ("mitsuba",)
VARIANT = "llvm_ad_rgb"
EXIT_UNAVAILABLE = 2
TAG = "peer-mitsuba"
DEFAULT_SCENES = ("pool.toml", "pool_sky.toml")
DEFAULT_SIZE = 64  # the equal-time error runs
DEFAULT_SECONDS = 10.0  # equal-time budget per renderer and scene
DEFAULT_REFERENCE_TIME = 300.0
REFERENCE_ALGORITHM = "vcm"
THROUGHPUT_SIZE = 256
THROUGHPUT_SPP = 16  # Mitsuba samples per pixel of one timed render at the throughput size
CHUNK_PATHS = 2**18  # Mitsuba camera paths per render of the equal-time runs
WATER_RESOLUTION = 128
SKY_ROWS = 1024
REL_EPS = 0.01  # relMAE denominator offset, as in the main bench
FIGURE = "peer_mitsuba.png"
SEED_OFFSET = 7_000_001  # Mitsuba's seeds: independent of jaxvcm's and of the reference's
INSTALL_HINT = ("pip install 'jaxvcm[peer]' (Mitsuba 3; its LLVM variants need libLLVM 17 "
                "or newer, e.g. Debian's libllvm19)")

# jaxvcm's static kinds (`Scene.materials.kind`, `Scene.lights.kind`); tests check them
# against the package's own values
MAT_DIFFUSE, MAT_DIELECTRIC, MAT_MIRROR = 0, 1, 2
LIGHT_RECT, LIGHT_SPHERE, LIGHT_SUN, LIGHT_SKY = 0, 1, 2, 3
PHASE_ISOTROPIC, PHASE_HG = 0, 1


class PeerUnavailable(RuntimeError):
    """The peer renderer cannot run here; the message is the one line the bench prints."""


def load_mitsuba(variant: str = VARIANT):
    """Import Mitsuba 3 and select `variant`; PeerUnavailable (one line) if it cannot."""
    try:
        import mitsuba as mi
    except ImportError as e:
        raise PeerUnavailable(f"Mitsuba 3 is not installed ({e}); {INSTALL_HINT}") from None
    try:
        mi.set_variant(variant)
        import drjit as dr

        x = dr.sum(mi.Float([1.0, 2.0]))  # a first kernel: the LLVM backend really works
        dr.eval(x)
        if float(x[0] if hasattr(x, "__len__") else x) != 3.0:
            raise RuntimeError("a test kernel computed the wrong sum")
    except Exception as e:  # noqa: BLE001 - any failure here means "no usable peer"
        msg = " ".join(str(e).split())[:200]
        raise PeerUnavailable(f"Mitsuba {getattr(mi, '__version__', '?')} cannot run its "
                              f"{variant} variant ({type(e).__name__}: {msg}); "
                              f"{INSTALL_HINT}") from None
    return mi


# ----------------------------------------------------------------------------- scene dict
def _rgb(x, channels: int = 3) -> dict:
    a = np.resize(np.asarray(x, np.float64).reshape(-1), channels)
    return {"type": "rgb", "value": [float(v) for v in a[:3]]}


def rect_to_world(p0, e1, e2) -> np.ndarray:
    """4x4 matrix taking Mitsuba's `rectangle` ([-1, 1]^2 at z = 0, normal +z) onto the
    parallelogram p0 + u e1 + v e2 (u, v in [0, 1]) with normal normalize(e1 x e2)."""
    p0, e1, e2 = (np.asarray(v, np.float64) for v in (p0, e1, e2))
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = 0.5 * e1, 0.5 * e2, n
    m[:3, 3] = p0 + 0.5 * (e1 + e2)
    return m


def sky_bitmap(radiance, rows: int = SKY_ROWS, cols: int = 8) -> np.ndarray:
    """[rows, cols, 3] lat-long image for Mitsuba's `envmap` (row 0 = +y): the radiance in
    the upper half (directions with y > 0), 0 in the lower half."""
    if rows % 2:
        raise ValueError("sky_bitmap: rows must be even")
    img = np.zeros((rows, cols, 3), np.float32)
    img[: rows // 2] = np.resize(np.asarray(radiance, np.float32).reshape(-1), 3)[:3]
    return img


def camera_spec(scene) -> dict:
    cam = scene.camera
    o = np.asarray(cam.origin, np.float64)
    f = np.asarray(cam.forward, np.float64)
    u = np.asarray(cam.up, np.float64)
    fov = math.degrees(2.0 * math.atan(float(cam.tan_half_fov)))
    return {"type": "perspective", "fov": fov, "fov_axis": "y",
            "near_clip": 1e-3, "far_clip": 1e4,
            "to_world": {"look_at": (o, o + f, u)},
            "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb",
                     "component_format": "float32"},
            "sampler": {"type": "independent", "sample_count": 1}}


def _material(scene, m: int) -> dict:
    mats = scene.materials
    kind = mats.kind[m]
    if kind == MAT_DIFFUSE:
        return {"type": "twosided",
                "bsdf": {"type": "diffuse", "reflectance": _rgb(mats.albedo[m])}}
    if kind == MAT_MIRROR:
        return {"type": "twosided",
                "bsdf": {"type": "conductor", "material": "none",
                         "specular_reflectance": _rgb(mats.albedo[m])}}
    if kind == MAT_DIELECTRIC:
        ior = float(np.asarray(mats.ior[m]).reshape(-1)[0])
        return {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0}
    raise ValueError(f"peer mitsuba: material kind {kind} has no Mitsuba counterpart")


def medium_spec(scene) -> dict:
    w = scene.water
    sa = np.resize(np.asarray(w.sigma_a, np.float64).reshape(-1), 3)
    ss = np.resize(np.asarray(w.sigma_s, np.float64).reshape(-1), 3)
    st = sa + ss
    albedo = np.where(st > 0, ss / np.where(st > 0, st, 1.0), 0.0)
    if w.phase_kind == PHASE_ISOTROPIC:
        phase = {"type": "isotropic"}
    elif w.phase_kind == PHASE_HG:
        phase = {"type": "hg", "g": float(w.g)}
    else:
        raise ValueError("peer mitsuba: the 'water' phase function has no Mitsuba "
                         "counterpart (use isotropic or hg)")
    return {"type": "homogeneous", "sigma_t": _rgb(st), "albedo": _rgb(albedo),
            "scale": 1.0, "phase": phase}


def scene_spec(scene, *, max_depth: int, rr_depth: int,
               water_resolution: int = WATER_RESOLUTION, sky_rows: int = SKY_ROWS) -> dict:
    """The Mitsuba 3 scene dict of a jaxvcm Scene, in plain Python and NumPy: `to_world`
    values are 4x4 arrays or {"look_at": (origin, target, up)}, the water surface is
    {"type": "mesh", "vertices", "normals", "faces", ...} and the sky's `bitmap` an array;
    `to_mitsuba` turns those into Mitsuba objects."""
    spec: dict = {"type": "scene",
                  "integrator": {"type": "volpath", "max_depth": int(max_depth),
                                 "rr_depth": int(rr_depth)},
                  "sensor": camera_spec(scene)}
    r = scene.rects
    p0, e1, e2 = (np.asarray(x, np.float64) for x in (r.p0, r.e1, r.e2))
    rmat, rlight = np.asarray(r.mat), np.asarray(r.light)
    lights = scene.lights
    lrad = np.asarray(lights.radiance, np.float64)
    for i in range(p0.shape[0]):
        shape = {"type": "rectangle", "to_world": rect_to_world(p0[i], e1[i], e2[i]),
                 "bsdf": _material(scene, int(rmat[i]))}
        if rlight[i] >= 0:
            shape["emitter"] = {"type": "area", "radiance": _rgb(lrad[rlight[i]])}
            spec[f"light_rect_{int(rlight[i])}"] = shape
        else:
            spec[f"rect_{i}"] = shape
    s = scene.spheres
    c, rad = np.asarray(s.center, np.float64), np.asarray(s.radius, np.float64)
    smat, slight = np.asarray(s.mat), np.asarray(s.light)
    for i in range(c.shape[0]):
        shape = {"type": "sphere", "center": c[i].tolist(), "radius": float(rad[i]),
                 "bsdf": _material(scene, int(smat[i]))}
        if slight[i] >= 0:
            shape["emitter"] = {"type": "area", "radiance": _rgb(lrad[slight[i]])}
        spec[f"sphere_{i}"] = shape
    ldir = np.asarray(lights.direction, np.float64)
    for k, kind in enumerate(lights.kind):
        if kind == LIGHT_SKY:
            spec[f"sky_{k}"] = {"type": "envmap", "bitmap": sky_bitmap(lrad[k], sky_rows)}
        elif kind == LIGHT_SUN:
            spec[f"sun_{k}"] = {"type": "directional", "direction": ldir[k].tolist(),
                                "irradiance": _rgb(lrad[k])}
    w = scene.water
    if w.enabled:
        V, N, F = jaxvcm.water_grid(scene, water_resolution)
        spec["water"] = {"type": "mesh", "vertices": V, "normals": N, "faces": F,
                         "bsdf": _material(scene, w.mat), "interior": medium_spec(scene)}
    return spec


# ----------------------------------------------------------------------------- Mitsuba
def _convert(mi, v):
    if isinstance(v, dict):
        if set(v) == {"look_at"}:
            o, t, u = (np.asarray(x, np.float64).tolist() for x in v["look_at"])
            return mi.ScalarTransform4f().look_at(origin=o, target=t, up=u)
        if v.get("type") == "mesh":
            return _mesh(mi, v)
        return {k: _convert(mi, x) for k, x in v.items()}
    if isinstance(v, np.ndarray) and v.shape == (4, 4):
        return mi.ScalarTransform4f(v.tolist())
    if isinstance(v, np.ndarray) and v.ndim == 3:
        return mi.Bitmap(np.ascontiguousarray(v, np.float32))
    return v


def _mesh(mi, m: dict):
    import drjit as dr

    V, N, F = (np.ascontiguousarray(m[k]) for k in ("vertices", "normals", "faces"))
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_convert(mi, m["bsdf"]))
    if "interior" in m:
        props["interior"] = mi.load_dict(_convert(mi, m["interior"]))
    mesh = mi.Mesh("water", vertex_count=V.shape[0], face_count=F.shape[0], props=props,
                   has_vertex_normals=True, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(V.astype(np.float32).T))
    params["vertex_normals"] = dr.ravel(mi.Normal3f(N.astype(np.float32).T))
    params["faces"] = dr.ravel(mi.Vector3u(F.astype(np.uint32).T))
    params.update()
    return mesh


def to_mitsuba(mi, spec: dict):
    """The loaded Mitsuba scene of `scene_spec`'s dict."""
    return mi.load_dict(_convert(mi, spec))


def mitsuba_render(mi, mscene, spp: int, seed: int) -> np.ndarray:
    """One Mitsuba render as a float64 [H, W, 3] array (waited for, copied to the host)."""
    img = mi.render(mscene, spp=int(spp), seed=int(seed))
    return np.asarray(img, dtype=np.float64)[..., :3]


# ----------------------------------------------------------------------------- measuring
def _jax_pass(scene, config, seed: int, i: int) -> np.ndarray:
    import jax

    img, _, _ = jaxvcm.render_pass_host(scene, jaxvcm.pass_key(seed, i), config, i)
    return np.asarray(jax.block_until_ready(img), dtype=np.float64)


def throughput(a, path: Path, mi, log) -> dict:
    """Camera paths/s of jaxvcm PT (one pass = W x H x spp paths) and of Mitsuba (one render
    = W x H x THROUGHPUT_SPP paths) at the throughput size, medians over `passes` timed
    passes / renders after one warm-up each, the two interleaved so that load from other
    processes hits both alike. jaxvcm twice: its render's pass (1 sample per pixel) and a
    pass of Mitsuba's batch (THROUGHPUT_SPP samples per pixel in one program: the same
    paths per timed call; a short pass after an idle gap pays the thread pool's cold
    start, which the interleaving gives every pass)."""
    n = THROUGHPUT_SIZE if not a.quick else a.size
    scene = jaxvcm.load_scene(path, width=n, height=n)
    config = jaxvcm.RenderConfig(algorithm="pt", max_depth=a.max_depth)
    batched = jaxvcm.RenderConfig(algorithm="pt", max_depth=a.max_depth, spp=THROUGHPUT_SPP)
    mscene = to_mitsuba(mi, scene_spec(scene, max_depth=a.max_depth, rr_depth=config.rr_depth))
    t0 = time.perf_counter()
    _jax_pass(scene, config, a.seed, 0)
    tj0 = time.perf_counter() - t0
    t0 = time.perf_counter()
    _jax_pass(scene, batched, a.seed, 0)
    tb0 = time.perf_counter() - t0
    t0 = time.perf_counter()
    mitsuba_render(mi, mscene, THROUGHPUT_SPP, a.seed + SEED_OFFSET)
    tm0 = time.perf_counter() - t0
    log(f"peer throughput {path.stem} {n}x{n} d{a.max_depth}: warm-up jaxvcm pt {tj0:.1f} s, "
        f"mitsuba {tm0:.1f} s; {a.throughput_passes} timed each, interleaved")
    tj, tm, tb = [], [], []
    for i in range(a.throughput_passes):
        t0 = time.perf_counter()
        _jax_pass(scene, config, a.seed, i + 1)
        tj.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        mitsuba_render(mi, mscene, THROUGHPUT_SPP, a.seed + SEED_OFFSET + i + 1)
        tm.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _jax_pass(scene, batched, a.seed, i + 1)
        tb.append(time.perf_counter() - t0)
    pj = n * n * config.spp / float(np.median(tj))
    pb = n * n * batched.spp / float(np.median(tb))
    pm = n * n * THROUGHPUT_SPP / float(np.median(tm))
    row = {"scene": path.stem, "width": n, "height": n, "max_depth": a.max_depth,
           "passes": a.throughput_passes,
           "jaxvcm": {"algorithm": "pt", "spp_per_pass": config.spp,
                      "warmup_s": tj0, "seconds": tj, "median_s": float(np.median(tj)),
                      "camera_paths_per_s": pj},
           "mitsuba": {"integrator": "volpath", "spp_per_render": THROUGHPUT_SPP,
                       "warmup_s": tm0, "seconds": tm, "median_s": float(np.median(tm)),
                       "camera_paths_per_s": pm},
           "mitsuba_over_jaxvcm": pm / pj,
           "jaxvcm_batched": {"algorithm": "pt", "spp_per_pass": batched.spp,
                              "warmup_s": tb0, "seconds": tb,
                              "median_s": float(np.median(tb)), "camera_paths_per_s": pb},
           "mitsuba_over_jaxvcm_batched": pm / pb}
    log(f"  jaxvcm pt {pj:,.0f} camera paths/s ({batched.spp} spp per pass: {pb:,.0f}), "
        f"mitsuba {pm:,.0f}: mitsuba {pm / pj:.3g}x ({pm / pb:.3g}x)")
    return row


def _mean_se(means: list[float], weights: list[float]) -> tuple[float, float]:
    """Weighted mean of per-pass image means and its standard error."""
    m, w = np.asarray(means), np.asarray(weights, np.float64)
    w = w / w.sum()
    mu = float(np.sum(w * m))
    if len(m) < 2:
        return mu, float("nan")
    # effective-sample-size estimate for unequal weights
    var = float(np.sum(w * (m - mu) ** 2)) / (1.0 - float(np.sum(w * w)))
    return mu, math.sqrt(var * float(np.sum(w * w)))


def _equal_time_jax(scene, config, seed: int, seconds: float) -> dict:
    _jax_pass(scene, config, seed, 0)  # compile / warm up
    acc, means, i = None, [], 0
    t0 = time.perf_counter()
    while True:
        img = _jax_pass(scene, config, seed, i + 1)
        acc = img if acc is None else acc + img
        means.append(float(img.mean()))
        i += 1
        t = time.perf_counter() - t0
        if t >= seconds:
            break
    mu, se = _mean_se(means, [1.0] * len(means))
    n = scene.camera.width * scene.camera.height * config.spp
    return {"image": acc / i, "passes": i, "seconds": t, "spp": i * config.spp,
            "camera_paths_per_s": i * n / t, "mean": mu, "mean_se": se}


def _equal_time_mitsuba(mi, mscene, w: int, h: int, seed: int, seconds: float) -> dict:
    spp = max(1, round(CHUNK_PATHS / (w * h)))
    mitsuba_render(mi, mscene, spp, seed)  # compile / warm up
    acc, means, i = None, [], 0
    t0 = time.perf_counter()
    while True:
        img = mitsuba_render(mi, mscene, spp, seed + i + 1)
        acc = img if acc is None else acc + img
        means.append(float(img.mean()))
        i += 1
        t = time.perf_counter() - t0
        if t >= seconds:
            break
    mu, se = _mean_se(means, [1.0] * len(means))
    return {"image": acc / i, "passes": i, "seconds": t, "spp": i * spp,
            "spp_per_render": spp, "camera_paths_per_s": i * spp * w * h / t,
            "mean": mu, "mean_se": se}


def _rel_rmse(img, ref) -> float:
    m = float(np.mean(ref))
    return float(np.sqrt(np.mean((img - ref) ** 2))) / m if m > 0 else float("nan")


def _rel_mae(img, ref) -> float:
    return float(np.mean(np.abs(img - ref) / (np.abs(ref) + REL_EPS)))


def equal_time(a, path: Path, mi, reference, log) -> dict:
    """Both renderers for `a.peer_seconds` each at the error size; relative RMSE against the
    jaxvcm VCM reference (`reference(scene_path, scene)` -> (image, meta, reused)) and the
    ratio of image means."""
    scene = jaxvcm.load_scene(path, width=a.size, height=a.size)
    w, h = scene.camera.width, scene.camera.height
    config = jaxvcm.RenderConfig(algorithm="pt", max_depth=a.max_depth)
    ref, meta, reused = reference(path, scene)
    mscene = to_mitsuba(mi, scene_spec(scene, max_depth=a.max_depth, rr_depth=config.rr_depth))
    log(f"peer equal time {path.stem} {w}x{h} d{a.max_depth}: {a.peer_seconds:g} s each")
    rj = _equal_time_jax(scene, config, a.seed, a.peer_seconds)
    rm = _equal_time_mitsuba(mi, mscene, w, h, a.seed + SEED_OFFSET, a.peer_seconds)
    ratio = rj["mean"] / rm["mean"] if rm["mean"] > 0 else float("nan")
    ratio_se = abs(ratio) * math.hypot(rj["mean_se"] / rj["mean"], rm["mean_se"] / rm["mean"])
    row = {"scene": path.stem, "width": w, "height": h, "max_depth": a.max_depth,
           "budget_s": a.peer_seconds,
           "reference": {**{k: meta.get(k) for k in (
               "algorithm", "passes", "seconds", "seed", "mean", "noise_rel_rmse")},
               "reused": reused}}
    images = [ref]
    for name, r in (("jaxvcm", rj), ("mitsuba", rm)):
        img = r.pop("image")
        images.append(img)
        r["rel_rmse"] = _rel_rmse(img, ref)
        r["rel_mae"] = _rel_mae(img, ref)
        r["mean_over_reference"] = r["mean"] / float(np.mean(ref))
        row[name] = r
    row["_images"] = images
    row["jaxvcm"]["algorithm"] = "pt"
    row["mean_ratio_pt_over_mitsuba"] = ratio
    row["mean_ratio_se"] = ratio_se
    log(f"  jaxvcm pt: {rj['spp']} spp in {rj['seconds']:.1f} s, relRMSE {rj['rel_rmse']:.4g}; "
        f"mitsuba: {rm['spp']} spp in {rm['seconds']:.1f} s, relRMSE {rm['rel_rmse']:.4g}; "
        f"mean ratio pt / mitsuba {ratio:.4f} +- {ratio_se:.4f}")
    return row


# ----------------------------------------------------------------------------- report
def write_figure(path: Path, grid: list) -> None:
    """Rows: scenes; columns: the jaxvcm VCM reference, jaxvcm PT and Mitsuba at equal time
    (sRGB previews, one exposure per row: the reference's 99th percentile at 1)."""
    from matplotlib.image import imsave

    pad = 2
    rows = []
    for ref, *imgs in grid:
        scale = 1.0 / max(float(np.percentile(ref, 99)), 1e-6)
        k = max(1, 256 // ref.shape[0])  # nearest-neighbour upscaling of small images
        tiles = [np.repeat(np.repeat(jaxvcm.to_srgb8(np.asarray(x, np.float32) * scale),
                                     k, axis=0), k, axis=1) for x in (ref, *imgs)]
        h = tiles[0].shape[0]
        gap = np.full((h, pad, 3), 255, np.uint8)
        rows.append(np.concatenate(sum(([t, gap] for t in tiles), [])[:-1], axis=1))
    wmax = max(r.shape[1] for r in rows)
    out = []
    for r in rows:
        out += [np.pad(r, ((0, 0), (0, wmax - r.shape[1]), (0, 0)), constant_values=255),
                np.full((pad, wmax, 3), 255, np.uint8)]
    img = np.concatenate(out[:-1], axis=0)
    with jaxvcm.atomic_path(str(path)) as tmp:
        imsave(tmp, img, format="png")


def _g(x, d=4) -> str:
    return "–" if x is None or not (isinstance(x, (int, float)) and math.isfinite(x)) \
        else f"{x:.{d}g}"


def markdown(res: dict) -> str:
    L = ["## Peer: Mitsuba 3", "",
         f"- {C.machine_line(res['machine'])}; Mitsuba {res['mitsuba_version']} "
         f"(`{res['variant']}`, `volpath`)",
         f"- command: `{res['command']}`",
         *([f"- load average (1, 5, 15 min) at the start / after the throughput rows / at "
            f"the end: {la.get('start')} / {la.get('after_throughput')} / {la.get('end')} "
            f"on {res['machine']['cpu_count']} CPUs"] if (la := res.get("load_average"))
           else []),
         f"- max depth {res['max_depth']} (both renderers count path segments), Russian "
         f"roulette from depth {res['rr_depth']} in both; Mitsuba's scene is built by "
         "`benchmarks/peer_mitsuba.py` from the loaded jaxvcm scene: the water heightfield "
         f"tessellated to a {res['water_resolution']}x{res['water_resolution']} vertex grid "
         "with analytic vertex normals (`jaxvcm.water_grid`), a smooth `dielectric` "
         "bounding a `homogeneous` medium, the same camera, lights and albedos, diffuse "
         "surfaces wrapped in `twosided` (ours shade both sides).", "",
         "What is matched and what is not:", "",
         "- *Matched:* camera (origin, view direction, up, vertical field of view, box pixel "
         "filter, image orientation checked), rectangles and their albedos, the one-sided "
         "rect light (radiance, size, orientation, black reflectance), the smooth dielectric "
         "(IOR 1.33, exact Fresnel in both), the homogeneous medium (Mitsuba: sigma_t = "
         "sigma_a + sigma_s and albedo sigma_s / sigma_t per RGB channel, isotropic "
         "phase), the maximum depth (both count segments). The basin's walls shade both "
         "sides in jaxvcm; Mitsuba's `diffuse` is one-sided, so it is wrapped in "
         "`twosided`: no pixels need to be excluded (the outer faces of the walls are in "
         "view).",
         "- *Approximated:* the water surface. jaxvcm intersects the analytic heightfield; "
         f"Mitsuba sees a {res['water_resolution']}x{res['water_resolution']} triangle grid "
         "(1.6 cm spacing; the shortest wave is 34 cm long, so heights are off by ~1e-4 m) "
         "and refracts about the interpolated analytic normals, which moves caustic "
         "filaments slightly and can leak a little energy at grazing angles. The sky "
         f"(radiance for y > 0 only) is an `envmap` of {SKY_ROWS} rows whose horizon is "
         f"blurred over one row ({180 / SKY_ROWS:.2f} degrees).",
         "- *Different by design (same expectation, different noise and cost):* Russian "
         "roulette from the same depth but with each renderer's own survival probability; "
         "jaxvcm samples medium distances by sigma_s of one channel and weights by "
         "transmittance, Mitsuba by sigma_t; Mitsuba's `volpath` is a unidirectional "
         "path tracer like jaxvcm PT (no next-event estimation through the water surface "
         "in either: the interface is delta).",
         "- *Batching:* one jaxvcm PT pass of its render is 1 sample per pixel (W x H "
         f"lanes, one XLA program); one Mitsuba render is {THROUGHPUT_SPP} samples per "
         "pixel (one Dr.Jit wavefront), each at its natural batch size; the throughput "
         f"rows add a jaxvcm pass of Mitsuba's batch ({THROUGHPUT_SPP} samples per pixel "
         "in one program, the same paths per timed call); all use all CPU threads, and all "
         "timings include the copy of the image to the host. Compilation is excluded "
         "(warm-up render first; warm-up seconds are in the JSON).",
         "- The machine is shared and noisy: the figures below are medians of one run, the "
         "renderers interleaved so that load from other processes hits them alike.",
         ""]
    tp = res.get("throughput") or []
    if tp:
        L += ["### Throughput", "",
              "Median wall seconds per pass (jaxvcm PT: its render's pass, 1 camera path "
              f"per pixel, and a pass of Mitsuba's batch, {THROUGHPUT_SPP} per pixel) / per "
              f"render (Mitsuba, {THROUGHPUT_SPP} spp), each after one warm-up, the three "
              "interleaved; camera paths/s = W x H x spp / median.", "",
              "| scene | size | depth | timed | jaxvcm spp / pass | jaxvcm PT s/pass "
              "| jaxvcm PT camera paths/s | Mitsuba s/render | Mitsuba camera paths/s "
              "| Mitsuba / jaxvcm |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for r in tp:
            m = r["mitsuba"]
            runs = [(r["jaxvcm"], r["mitsuba_over_jaxvcm"])]
            if "jaxvcm_batched" in r:
                runs.append((r["jaxvcm_batched"], r["mitsuba_over_jaxvcm_batched"]))
            for j, ratio in runs:
                L.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['max_depth']} | "
                         f"{r['passes']} | {j['spp_per_pass']} | {j['median_s']:.3f} | "
                         f"{j['camera_paths_per_s']:,.0f} | {m['median_s']:.3f} | "
                         f"{m['camera_paths_per_s']:,.0f} | **{ratio:.3g}x** |")
        L.append("")
    et = res.get("equal_time") or []
    if et:
        L += ["### Equal time: error against a jaxvcm VCM reference, and image means", "",
              "Each renderer for the same wall-clock budget (compilation excluded), images "
              "averaged on the host. relRMSE = RMSE / mean(reference) over all pixels and "
              "channels; the reference is a long jaxvcm VCM render (its own noise: *ref. "
              "noise*, so errors near it say little; any systematic difference between "
              "the two scene descriptions shows as an error floor for Mitsuba). *mean PT / "
              "Mitsuba*: ratio of the image means, +- one standard error from the per-pass "
              "means.", "",
              "| scene | size | budget s | jaxvcm PT spp | Mitsuba spp | jaxvcm PT relRMSE "
              "| Mitsuba relRMSE | ref. noise (rel) | jaxvcm PT relMAE | Mitsuba relMAE "
              "| PT / ref mean | Mitsuba / ref mean | mean PT / Mitsuba |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in et:
            j, m, ref = r["jaxvcm"], r["mitsuba"], r["reference"]
            L.append(f"| {r['scene']} | {r['width']}x{r['height']} | {r['budget_s']:g} | "
                     f"{j['spp']} | {m['spp']} | {_g(j['rel_rmse'])} | {_g(m['rel_rmse'])} | "
                     f"{_g(ref.get('noise_rel_rmse'), 3)} | {_g(j['rel_mae'])} | "
                     f"{_g(m['rel_mae'])} | {_g(j['mean_over_reference'])} | "
                     f"{_g(m['mean_over_reference'])} | "
                     f"**{r['mean_ratio_pt_over_mitsuba']:.4f} +- {r['mean_ratio_se']:.4f}** |")
        L.append("")
        L += ["References:", ""]
        for r in et:
            ref = r["reference"]
            L.append(f"- {r['scene']}: jaxvcm {ref['algorithm']}, {r['width']}x{r['height']}, "
                     f"{ref['passes']} passes in {ref['seconds']} s (seed {ref['seed']}), "
                     f"noise rel {_g(ref.get('noise_rel_rmse'), 3)}"
                     + ("" if ref["reused"] else " (rendered in this run)"))
        L += ["", f"![reference, jaxvcm PT, Mitsuba at equal time]({FIGURE})", "",
              f"`{FIGURE}`: per scene (rows) the jaxvcm VCM reference, jaxvcm PT and "
              "Mitsuba after the same wall time (one exposure per row).", ""]
    return "\n".join(L)


def summary_lines(res: dict) -> list[str]:
    out = []
    for r in res.get("throughput") or []:
        out.append(f"peer mitsuba: {r['scene']} {r['width']}x{r['height']} d{r['max_depth']}: "
                   f"jaxvcm PT {r['jaxvcm']['camera_paths_per_s']:,.0f} camera paths/s, "
                   f"Mitsuba {r['mitsuba']['camera_paths_per_s']:,.0f}; Mitsuba "
                   f"{r['mitsuba_over_jaxvcm']:.3g}x faster"
                   + (f" ({r['jaxvcm_batched']['spp_per_pass']} spp per jaxvcm pass: "
                      f"{r['jaxvcm_batched']['camera_paths_per_s']:,.0f}, "
                      f"{r['mitsuba_over_jaxvcm_batched']:.3g}x)" if "jaxvcm_batched" in r
                      else ""))
    for r in res.get("equal_time") or []:
        out.append(f"peer mitsuba: {r['scene']} {r['width']}x{r['height']} {r['budget_s']:g} s "
                   f"each: relRMSE vs jaxvcm VCM reference: jaxvcm PT "
                   f"{_g(r['jaxvcm']['rel_rmse'])}, Mitsuba {_g(r['mitsuba']['rel_rmse'])}; "
                   f"image mean PT / Mitsuba {r['mean_ratio_pt_over_mitsuba']:.4f} +- "
                   f"{r['mean_ratio_se']:.4f}")
    return out


def _loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):  # pragma: no cover - not on every platform
        return None


def run_peer(a, argv, log, reference) -> int:
    """`--peer mitsuba`: measure, print the summary, write the section and the JSON.
    `reference(a, scene_path, scene)` supplies the jaxvcm reference image. Returns the exit
    status (EXIT_UNAVAILABLE with one line on stderr when Mitsuba cannot run)."""
    import sys

    try:
        mi = load_mitsuba(a.peer_variant)
    except PeerUnavailable as e:
        print(f"jaxvcm: bench --peer mitsuba: {e}", file=sys.stderr, flush=True)
        return EXIT_UNAVAILABLE
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "mitsuba_version": mi.__version__, "variant": a.peer_variant,
           "max_depth": a.max_depth, "rr_depth": jaxvcm.RenderConfig().rr_depth,
           "water_resolution": WATER_RESOLUTION, "seed": a.seed,
           "throughput": [], "equal_time": [], "load_average": {"start": _loadavg()}}
    if a.throughput_passes > 0:
        res["throughput"].append(throughput(a, a.scene_paths[0], mi, log))
    res["load_average"]["after_throughput"] = _loadavg()
    grid = []
    for path in a.scene_paths:
        row = equal_time(a, path, mi, lambda p, s: reference(a, p, s), log)
        grid.append(row.pop("_images"))
        res["equal_time"].append(row)
    if grid:
        png = a.out.parent / FIGURE
        write_figure(png, grid)
        log(f"figure -> {png}")
    res["load_average"]["end"] = _loadavg()
    body = markdown(res)
    C.upsert_section(a.out, TAG, body)
    C.write_json(a.out.with_name(f"{a.out.stem}_{TAG}.json"), res)
    for line in summary_lines(res):
        print(line)
    log(f"report -> {a.out}")
    return 0
