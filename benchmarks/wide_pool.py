"""Light under the water from far away: the wide flat sunlit pool with floor <-> surface
interreflection against its closed form, at equal wall time, with no aim and no pilot pass.

The pool of `benchmarks/aim_sweep.py` at its widest (120 m, purely absorbing water 1.2 m
deep, a floor of albedo 0.7, black walls, the sun 14 degrees from the zenith), the camera
3 m above the centre looking straight down (2 degree field of view, 8 x 8 pixels), max
depth 10. Beside the sun's direct light on the floor, the floor's light goes up, is
reflected back down by the surface (Fresnel inside the critical angle, totally beyond it)
and lights the floor again metres away: light that enters the water far from the view.
A path camera -> surface -> floor -> (surface -> floor)^j -> surface -> sun has 4 + 2 j
segments, so max depth D keeps j <= (D - 4) // 2 (3 round trips at depth 10), and

    E[L] = T0 / eta^2 exp(-sigma_a d) L_f,
    L_f  = (a / pi) E cos_i T(i) exp(-sigma_a d / cos_t) sum_{j <= 3} ((a / pi) K)^j

(`jaxvcm.sun_floor_radiance`; T0 / eta^2: the floor's radiance leaving the water at
normal incidence; the 1 degree half-angle of the view changes the slant by < 2e-4). The
finite pool loses only rays that travel more than 60 m sideways in a 2.4 m round trip
(theta > 87.7 degrees in the water): a fraction below 1e-4 of one bounce.

Every algorithm renders for the same wall time after a warm-up pass (default radius, no
`aim`); reported per algorithm: passes, the relative error of the image mean per channel
with its standard error (from the spread of the passes' image means), and the relRMSE
over pixels and channels. `jaxvcm bench --wide-pool [--wide-seconds S]` writes the section
'Light from far away: the wide sunlit pool' of docs/benchmarks.md.
"""

from __future__ import annotations

import math
import time

import numpy as np

import jaxvcm

from . import aim_sweep as _as

WIDTH = 120.0
MAX_DEPTH = 10
DEFAULT_ALGORITHMS = ["vcm", "ppm", "pt+mnee", "bdpt+mnee", "vcm+mnee"]
TAG = "wide-pool"


def expected(max_depth: int = MAX_DEPTH) -> np.ndarray:
    """E[L] [3] of the module doc: the same for every pixel."""
    sa = np.asarray(_as.SIGMA_A, np.float64)
    L_f = jaxvcm.sun_floor_radiance(_as.DEPTH, sa, _as.ETA, _as.ALBEDO, _as.E, -_as.SUN[1],
                                    (max_depth - 4) // 2)
    T0 = 1.0 - ((_as.ETA - 1.0) / (_as.ETA + 1.0)) ** 2
    return T0 / _as.ETA**2 * np.exp(-sa * _as.DEPTH) * L_f


def run(alg: str, seconds: float, seed: int = 0) -> dict:
    from .bench import render_config
    scene = jaxvcm.scene_from_dict(_as.pool(WIDTH))
    cfg = render_config(alg, max_depth=MAX_DEPTH)
    img, _, cfg = jaxvcm.render_pass_host(scene, jaxvcm.pass_key(seed, 0), cfg, 0)  # compile
    total = np.zeros_like(np.asarray(img, np.float64))
    means = []
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        img, diag, cfg = jaxvcm.render_pass_host(scene, jaxvcm.pass_key(seed, n + 1), cfg, n + 1)
        im = np.asarray(img, np.float64)
        total += im
        means.append(im.mean(axis=(0, 1)))
        n += 1
    dt = time.perf_counter() - t0
    ref = expected()
    m = np.asarray(means)
    rel = m.mean(0) / ref - 1.0
    se = (m.std(0, ddof=1) / math.sqrt(n) / ref) if n > 1 else np.full(3, np.nan)
    rmse = float(np.sqrt(np.mean((total / n / ref - 1.0) ** 2)))
    return {"algorithm": alg, "passes": n, "seconds": dt, "rel_error": rel.tolist(),
            "rel_se": se.tolist(), "rel_rmse": rmse}


def run_wide(a, argv, log) -> dict:
    """`jaxvcm bench --wide-pool`: every algorithm for the same seconds, one run."""
    from . import _common as C
    seconds = 2.0 if a.quick else a.wide_seconds
    res = {"machine": C.machine(), "command": " ".join(["jaxvcm", "bench", *argv]),
           "seconds": seconds, "max_depth": MAX_DEPTH, "expected": expected().tolist(),
           "rows": []}
    for alg in a.algorithms:
        r = run(alg, seconds, a.seed)
        res["rows"].append(r)
        log(f"wide pool: {alg}: {r['passes']} passes, rel. error "
            + " / ".join(f"{e:+.3f}" for e in r["rel_error"]) + f", relRMSE {r['rel_rmse']:.3f}")
    C.publish(a.out, TAG, res, markdown(res), log)
    return res


def markdown(res: dict) -> str:
    from . import _common as C
    L = C.section_head("Light from far away: the wide sunlit pool", res) + [
        f"- The flat sunlit pool of `benchmarks/wide_pool.py`: {WIDTH:g} m wide, camera 3 m "
        "above the centre looking straight down (2 degrees, 8x8), max depth "
        f"{res['max_depth']}, so the floor under the camera is lit by the sun directly and "
        "by up to 3 floor -> surface -> floor round trips of light that entered the water "
        "metres away. No aim, no pilot pass, default radius. Each row renders for "
        f"{res['seconds']:g} s of wall time after a warm-up pass; errors against the closed "
        "form (`jaxvcm.sun_floor_radiance`): the image mean's relative error per channel "
        "R / G / B with its standard error, and relRMSE over pixels and channels. Target: "
        "within 1 % in every channel after 60 s.", "",
        "| algorithm | passes | rel. error of the mean R / G / B | its SE | relRMSE |",
        "|---|---|---|---|---|"]
    for r in res["rows"]:
        L.append(f"| {r['algorithm']} | {r['passes']} | "
                 + " / ".join(f"{100 * e:+.2f} %" for e in r["rel_error"]) + " | "
                 + " / ".join(f"{100 * e:.2f} %" for e in r["rel_se"]) + " | "
                 f"{r['rel_rmse']:.4f} |")
    L.append("")
    ok = [r["algorithm"] for r in res["rows"]
          if all(abs(e) + 2 * s < 0.01 for e, s in zip(r["rel_error"], r["rel_se"]))]
    L.append(f"- Within 1 % in every channel (error + 2 SE): {', '.join(ok) or 'none'}. "
             "Without manifold NEE the light of the floor is found only by the photons "
             "that land within a merging radius of a floor point the camera sees (and by "
             "nothing else: the sun cannot be hit, and no connection passes the surface). "
             "The default radius is a fraction of the view radius (the ~10 cm of floor "
             "the camera sees), raised to the 2.2 cm the float32 hash grid resolves at the "
             "pool's 120 m extent (docs/design/merging.md): over the 14,400 m^2 pool a "
             "pass's 64 photons land in such a disk about once in several thousand passes, "
             "so vcm's and ppm's means after 60 s are heavy-tailed, far below the value, and "
             "their SE (from passes that have not seen the rare large ones) says nothing; "
             "aiming the photons at the view (`--aim-view`, the scale sweep) is merging's "
             "route here. With manifold NEE every floor vertex of a camera path connects "
             "to the sun through the surface, and the round trips are ordinary scattering "
             "between those vertices: no bias is left.")
    L.append("")
    return "\n".join(L) + "\n"
