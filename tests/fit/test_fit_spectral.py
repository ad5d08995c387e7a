"""Spectral fit configs and the spectral switches of the CLI (`jaxvcm fit` with
mode = "spectral", `jaxvcm render --spectral`).

(a) bad spectral configs give one line naming the field and exit status 2, before any
    rendering; (b) a tiny spectral fit through the CLI recovers a known CDOM absorption
    from colours computed with colour-science (not rendered); (c) `render --spectral`
    writes a finite, correctly tinted image; (d) the WaterModel's a_w_scale leaf.
Expected values are derived in the comments.
"""

from __future__ import annotations

import json
from pathlib import Path

import colour
import jax
import numpy as np
import pytest

import jaxvcm
from jaxvcm._fit import load_fit_config
from jaxvcm._spectral import WaterModel, pope_fry_table
from jaxvcm.cli import main

ROOT = Path(__file__).resolve().parents[2]
POOL_SKY = ROOT / "scenes" / "pool_sky.toml"
CMFS = "CIE 1931 2 Degree Standard Observer"


def emitter_scene_toml(L: float, size: int) -> str:
    """Camera in the water at the origin looking straight down (fov 1 deg) at an upward
    white (D65) emitting floor L metres below; no surface crossing, no scattering
    configured: every camera path sees Le(lambda) exp(-sigma_a(lambda) L)."""
    return f"""
[camera]
position = [0.0, 0.0, 0.0]
target = [0.0, -1.0, 0.0]
up = [0.0, 0.0, -1.0]
fov = 1.0
width = {size}
height = {size}

[water]
level = 0.5
sigma_a = 0.1
sigma_s = 0.0
ior = 1.33
footprint = [-2.0, 2.0, -2.0, 2.0]
floor = {-L - 0.01}

[[lights]]
type = "rect"
center = [0.0, {-L}, 0.0]
normal = [0.0, 1.0, 0.0]
size = [4.0, 4.0]
radiance = [1.0, 1.0, 1.0]
"""


def beer_lambert_xyz(L: float, a_cdom: float, S: float = 0.015) -> np.ndarray:
    """XYZ (Y = 1 for white) of D65 through L metres of water with sigma_a = a_w (Pope &
    Fry, the shipped CSV) + a_cdom exp(-S (lambda - 440)), directly with colour-science."""
    wl, a = pope_fry_table()
    T = np.exp(-(a + a_cdom * np.exp(-S * (wl - 440.0))) * L)
    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        return colour.sd_to_XYZ(colour.SpectralDistribution(T, wl), colour.MSDS_CMFS[CMFS],
                                colour.SDS_ILLUMINANTS["D65"]) / 100.0


# ------------------------------------------------------------------ (a) config errors
GOOD = """
mode = "spectral"
space = "xyz"
params = ["a_cdom"]
[render]
passes = 1
width = 8
height = 8
[scenes.pool]
file = "{scene}"
[init]
a_cdom = 0.05
[[regions]]
name = "floor"
scene = "pool"
rect = [2, 2, 6, 6]
target = [0.1, 0.2, 0.3]
"""

# (replacement of a line or table of GOOD, the field the one-line error must name)
BAD = {
    "mode": ('mode = "hyper"', "mode"),
    "params_missing": ("params = REMOVE", "params"),
    "params_unknown": ('params = ["sigma_a"]', "params[0]"),
    "params_twice": ('params = ["a_cdom", "a_cdom"]', "params[1]"),
    "params_empty": ("params = []", "params"),
    "linear_not_fitted": ('linear = ["b_p"]', "linear[0]"),
    "init_not_fitted": ("[init]\nb_p = 0.1", "init.b_p"),
    "init_zero_log": ("[init]\na_cdom = 0.0", "init.a_cdom"),
    "init_out_of_range": ("[init]\na_cdom = 2e6", "init.a_cdom"),  # (1e-9, 1e6) 1/m
    "water_n_p": ("[water]\nn_p = 5.0", "water.n_p"),  # [0, 4]: 4 is Rayleigh
    "max_delta_e": ("[solver]\nmax_delta_e = -1.0", "solver.max_delta_e"),
    "water_unknown": ("[water]\ncolour = 1", "water.colour"),
    "water_g": ("[water]\ng = 1.5", "water.g"),
    "water_negative": ("[water]\nb_p = -0.1", "water.b_p"),
    "water_flag": ("[water]\npure_scattering = 1", "water.pure_scattering"),
    "n_wavelengths": ("[spectral]\nn_wavelengths = 0", "spectral.n_wavelengths"),
    "ior": ('[spectral]\nior = "glass"', "spectral.ior"),
    "sun": ('[spectral]\nsun = "A"', "spectral.sun"),
    "free_in_spectral": ('[solver]\nfree = "sigma_a"', "solver.free"),
    "rgb_with_params": ('mode = "rgb"', "params"),  # spectral-only key in an RGB config
}


def _edit(text: str, edit: str) -> str:
    lines = text.strip("\n").splitlines()
    head = edit.splitlines()[0]
    if head.startswith("["):  # a table: replace it if present, else append it
        if head in lines:
            i = lines.index(head)
            j = i + 1
            while j < len(lines) and not lines[j].startswith("["):
                j += 1
            lines[i:j] = edit.splitlines()
        else:
            lines += edit.splitlines()
    else:
        key = head.split("=")[0].strip()
        i = next((k for k, ln in enumerate(lines) if ln.startswith(key + " =")), None)
        if i is None:
            lines.insert(0, head)
        elif edit.endswith("REMOVE"):
            del lines[i]
        else:
            lines[i] = head
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("case", sorted(BAD), ids=sorted(BAD))
def test_bad_spectral_config_one_line(case, tmp_path, capsys):
    edit, field = BAD[case]
    p = tmp_path / f"{case}.toml"
    p.write_text(_edit(GOOD.format(scene=POOL_SKY.as_posix()), edit))
    out = tmp_path / "out"
    rc = main(["fit", str(p), "--out", str(out)])
    _, err = capsys.readouterr()
    lines = err.splitlines()
    assert rc == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"jaxvcm: error: {p}: {field}: "), lines[0]
    assert not out.exists()


def test_good_spectral_config_parses(tmp_path):
    # defaults: 8 wavelengths, the Daimon & Masumura index, pure water with the [init]
    # value for the fitted leaf; the scene is upsampled to a SpectralScene
    p = tmp_path / "good.toml"
    p.write_text(GOOD.format(scene=POOL_SKY.as_posix())
                 + '[water]\nS = 0.017\npure_scattering = false\n')
    kw = load_fit_config(p)
    assert kw["mode"] == "spectral" and kw["params"] == ["a_cdom"] and kw["linear"] == []
    assert kw["init"] == {"a_cdom": 0.05} and kw["truth"] is None
    sp = kw["spectral"]["pool"]
    assert isinstance(sp, jaxvcm.SpectralScene) and sp.n_wavelengths == 8
    assert abs(float(sp.ior) - 1.33468) < 1e-4
    assert abs(float(sp.water.S) - 0.017) < 1e-6 and not sp.water.pure_scattering
    # a linear parameter may start at 0 (pure water's a_flat)
    text = _edit(GOOD.format(scene=POOL_SKY.as_posix()), 'params = ["a_flat"]')
    p.write_text(_edit(text.replace("a_cdom = 0.05", ""), 'linear = ["a_flat"]'))
    kw = load_fit_config(p)
    assert kw["init"] == {"a_flat": 0.0} and kw["linear"] == ["a_flat"]


# ------------------------------------------------------------------ (b) tiny fit via CLI
def test_cli_spectral_fit_recovers_cdom(tmp_path):
    """Target: the colour of D65 through L = 2 m of water with a_cdom = 0.1 /m (S = 0.015)
    on top of Pope & Fry, from colour-science (beer_lambert_xyz), not from a render. The
    fit starts at a_cdom = 0.02 (log space) and renders the emitter scene (2x2 pixels, 8
    passes of 32 wavelengths, PT max_depth 2, pure-water scattering off).

    Tolerance: the only noise is the wavelength sampling (every pixel sees the same path);
    a NumPy model of the estimator (8 passes x 32 stratified wavelengths, uniform offsets,
    the same XYZ residuals with 1% uncertainties), fitted 100 times, recovers a_cdom =
    0.09988 +- 0.00018 (max error 0.0006); with dense wavelengths 0.09985 (the renderer
    integrates 380-720 nm, colour-science 360-830 nm). Bound: |a_cdom - 0.1| < 0.002, i.e.
    2% (> 10 standard deviations); the initial guess is 80% off.

    Steps: the last ones are taken at float32's noise floor of the loss, where
    Levenberg-Marquardt rejects steps on round-off alone, so their number follows XLA's
    code generation: 8 steps under XLA's default settings, 30 under the suite's compile
    settings (`tests/conftest.py`), with the same a_cdom to 4 digits; max_steps 40."""
    L, truth = 2.0, 0.1
    (tmp_path / "emitter.toml").write_text(emitter_scene_toml(L, 2))
    t = beer_lambert_xyz(L, truth)
    cfg = tmp_path / "fit.toml"
    cfg.write_text(f"""
mode = "spectral"
space = "xyz"
params = ["a_cdom"]
[render]
algorithm = "pt"
max_depth = 2
passes = 8
seed = 2
[spectral]
n_wavelengths = 32
[water]
S = 0.015
pure_scattering = false
[init]
a_cdom = 0.02
[truth]
a_cdom = {truth}
[solver]
max_steps = 40
rtol = 1e-3
atol = 1e-3
[scenes.emitter]
file = "emitter.toml"
[[regions]]
name = "floor"
scene = "emitter"
rect = [0, 0, 2, 2]
target = [{t[0]!r}, {t[1]!r}, {t[2]!r}]
""")
    out = tmp_path / "out"
    rc = main(["fit", str(cfg), "--out", str(out), "--quiet"])
    assert rc == 0
    res = json.loads((out / "fit.json").read_text())
    assert res["mode"] == "spectral" and res["result"] == "successful"
    assert res["converged"] is True and res["problems"] == [] and res["at_bound"] == {}
    a = res["params"]["a_cdom"]
    assert abs(a - truth) < 0.002, res["params"]
    assert res["init"]["a_cdom"] == 0.02
    # the initial colour is visibly off (80% less CDOM: Z higher by ~ exp(0.08 * 2 * 0.8)
    # - 1 ~ 14% in the blue), the fitted one is not
    assert res["regions"][0]["delta_e2000_initial"] > 3.0
    assert res["regions"][0]["delta_e2000"] < 0.3
    assert 0 < res["params_sd"]["a_cdom"] < 0.01
    assert (out / "fit.png").stat().st_size > 10_000


# ------------------------------------------------------------------ (c) render --spectral
def test_cli_render_spectral(tmp_path, capsys):
    """The emitter seen through L = 4 m of pure water: Pope & Fry absorbs red (0.3-0.6 /m)
    far more than green (0.05) and blue (0.01), so the linear-sRGB image is blue-green:
    B > G > R on every pixel. The colour-science colour of 4 m, beer_lambert_xyz(4, 0), is
    linear sRGB (0.268, 0.823, 0.993). Every pixel of a pass sees the same wavelengths and
    path length, so the only noise is the wavelength sampling: a NumPy model of 4 passes x 8
    stratified wavelengths gives (0.268 +- 0.020, 0.823 +- 0.006, 0.992 +- 0.007) and never
    broke the order in 20000 draws (the B - G gap is > 10 standard deviations). The JSON
    records the spectral mode."""
    from jaxvcm import _io

    scene = tmp_path / "emitter.toml"
    scene.write_text(emitter_scene_toml(4.0, 4))
    exr = tmp_path / "s.exr"
    rc = main(["render", str(scene), "--spectral", "--wavelengths", "8", "--passes", "4",
               "--algorithm", "pt", "--max-depth", "2", "--out", str(exr), "--quiet"])
    assert rc == 0
    img = _io.read_exr(exr)
    assert img.shape == (4, 4, 3) and np.all(np.isfinite(img))
    assert np.all(img[..., 2] > img[..., 1]) and np.all(img[..., 1] > img[..., 0])
    meta = json.loads(exr.with_suffix(".json").read_text())
    assert meta["mode"] == "spectral" and meta["n_wavelengths"] == 8 and meta["nonfinite"] == 0
    assert exr.with_suffix(".png").stat().st_size > 0
    ref = colour.XYZ_to_RGB(beer_lambert_xyz(4.0, 0.0), "sRGB")
    assert ref[2] > ref[1] > ref[0]
    # argument errors: one line, exit status 2
    capsys.readouterr()
    for args, field in ((["--spectral", "--time", "1"], "--time"),
                        (["--wavelengths", "4"], "--wavelengths"),
                        (["--spectral", "--water", "colour=1"], "--water")):
        rc = main(["render", str(scene), "--out", str(tmp_path / "e.exr"), *args])
        err = capsys.readouterr().err.splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith(f"jaxvcm: error: {field}"), err


# ------------------------------------------------------------------ (d) a_w_scale
def test_a_w_scale_multiplies_pope_fry():
    # sigma_a(550) = a_w_scale * 0.0565 (Pope & Fry at 550 nm) + a_flat; default scale 1;
    # d sigma_a(550) / d a_w_scale = a_w(550) = 0.0565
    lam = np.float64(550.0)
    assert abs(float(WaterModel().sigma_a(lam)) - 0.0565) < 1e-12
    assert abs(float(WaterModel(a_w_scale=2.0, a_flat=0.01).sigma_a(lam)) - 0.123) < 1e-12
    g = jax.grad(lambda s: WaterModel(a_w_scale=s).sigma_a(lam))(1.0)
    assert abs(float(g) - 0.0565) < 1e-12
    # switched off with the pure-water term
    assert float(WaterModel(a_w_scale=3.0, pure_absorption=False).sigma_a(lam)) == 0.0


# ---------------------------------------------------------------- (e) spectral Jacobians vs FD
SPEC_PARAMS = ("a_cdom", "a_flat", "a_w_scale", "S", "b_p", "n_p", "g")  # every fittable leaf
N_SMOOTH = 4  # absorption-only parameters come first
SPEC_REGIONS = ((3, 4, 9, 9), (3, 8, 9, 11), (1, 4, 3, 9))  # floor, near floor, left wall


def test_spectral_jacobian_matches_central_differences():
    """jax.jacfwd of spectral region colours (XYZ of 3 regions of pool_sky, 12x12, PT,
    max_depth 4, 4 wavelengths, one pass per key) w.r.t. theta = ln of every fittable
    WaterModel leaf (a_cdom, a_flat, a_w_scale, S, b_p, n_p, g) vs central differences of
    the same function with the same key.
    The four absorption parameters (a_cdom, a_flat, a_w_scale, the CDOM slope S) only
    weight paths (the sampled distances depend on the scattering alone), so per key
    FD - J is the O(h^2) term, h^2 |(sigma d)^2 - sigma d| / 6 < 1e-3 relative for h = 0.05
    and sigma d < 3 (red light through ~2.5 m of water), plus float32 rounding ~1e-7 / (2 h):
    tolerance 1% of |J| + 2e-6 per key. b_p and n_p move the sampled scattering distances
    and g the sampled phase directions, so with common keys those functions have jumps:
    means over 16 keys within 4.5 standard errors of the per-key difference + 3% (h = 0.2,
    0.1 for g so that HG's g e^h stays below 1).
    Truth: a_cdom 0.05, a_flat 0.02, b_p 0.3 (raised so its derivative is resolved),
    a_w_scale 1 (Pope & Fry), S 0.015 /nm and n_p 1 (the WaterModel defaults), g 0.8."""
    import dataclasses

    import jax.numpy as jnp

    from jaxvcm import RenderConfig
    from jaxvcm._spectral import render_pass_spectral, spectral_scene

    scene = jaxvcm.load_scene(POOL_SKY, width=12, height=12)
    p0 = {"a_cdom": 0.05, "a_flat": 0.02, "a_w_scale": 1.0, "S": 0.015, "b_p": 0.3,
          "n_p": 1.0, "g": 0.8}
    sp = spectral_scene(scene, WaterModel(**p0), n_wavelengths=4)
    dt = sp.scene.bounds.dtype
    cfg = RenderConfig(algorithm="pt", max_depth=4, rr_depth=100)

    def colours(theta, key):
        vals = jnp.exp(theta)
        water = dataclasses.replace(sp.water, **{n: vals[j].astype(dt)
                                                 for j, n in enumerate(SPEC_PARAMS)})
        xyz, _ = render_pass_spectral(dataclasses.replace(sp, water=water), key, cfg)
        return jnp.stack([xyz[y0:y1, x0:x1].mean((0, 1)) for x0, y0, x1, y1 in SPEC_REGIONS]
                         ).reshape(-1).astype(jnp.float64)

    nk = 16
    keys = jnp.stack([jaxvcm.pass_key(5, k) for k in range(nk)])
    val_jac = jax.jit(jax.vmap(lambda t, k: jax.jacfwd(lambda u: (colours(u, k),) * 2,
                                                       has_aux=True)(t), in_axes=(None, 0)))
    theta0 = jnp.log(jnp.asarray([p0[n] for n in SPEC_PARAMS], dt))
    n = len(SPEC_PARAMS)
    h = np.array([0.05] * N_SMOOTH + [0.2, 0.2, 0.1])  # g e^0.1 = 0.88 stays < 1
    J, _ = val_jac(theta0, keys)
    J = np.asarray(J, np.float64)  # [keys, 9, n]
    cols = []
    for j in range(n):
        e = jnp.zeros(n, dt).at[j].set(jnp.asarray(h[j], dt))
        _, fp = val_jac(theta0 + e, keys)
        _, fm = val_jac(theta0 - e, keys)
        cols.append((np.asarray(fp, np.float64) - np.asarray(fm, np.float64)) / (2 * h[j]))
    FD = np.stack(cols, -1)
    assert np.all(np.isfinite(J))
    sm = slice(0, N_SMOOTH)
    np.testing.assert_allclose(J[..., sm], FD[..., sm], rtol=0.01, atol=2e-6)
    # non-trivial: a_cdom, a_flat, a_w_scale darken the floor's Y (XYZ row 1 of region 0);
    # a steeper CDOM slope S removes absorption (exp(-S (l - 440)) falls faster above 440)
    jy = J[:, 1, :N_SMOOTH].mean(0)
    assert np.all(jy[:3] < -1e-4) and jy[3] > 1e-5, jy
    d = J[..., N_SMOOTH:] - FD[..., N_SMOOTH:]
    se = d.std(0, ddof=1) / np.sqrt(nk)
    allow = 0.03 * np.abs(FD[..., N_SMOOTH:].mean(0)) + 1e-5
    assert np.all(np.abs(d.mean(0)) <= 4.5 * se + allow), (
        J[..., N_SMOOTH:].mean(0), FD[..., N_SMOOTH:].mean(0), se)
    # and the b_p derivative is resolved somewhere (the wall's in-scattering)
    jb = J[..., N_SMOOTH].mean(0)
    assert np.any(np.abs(jb) > 3 * J[..., N_SMOOTH].std(0, ddof=1) / np.sqrt(nk)), jb
