"""Sampling routines: every pdf integrates to one, and every sampler matches its pdf.

(a) Normalisation: the pdf is integrated numerically in float64 (composite Gauss-Legendre
    over the sphere / hemisphere / light / distance range) and must give 1 (to 1e-6,
    the quadrature being good to ~1e-9).
(b) Goodness of fit: N = 200k samples drawn with the renderer's float32 from fixed-seed
    uniforms are binned (directions in (cos theta, phi), area lights in their (u, v),
    distances in t); the expected count of a bin is N times the integral of the pdf over
    it (same quadrature); bins expected below 5 are pooled; Pearson's chi-square must give
    p > 1e-4 (the test is deterministic given the seed; 1e-4 leaves room for a seed change).
    Power: deliberately mismatched pdfs must be rejected at p < 1e-6 (`test_*wrong*`), so
    the chi-square machinery can fail.
Directions are sampled in a local frame with z along the normal / propagation axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import _lights as Lt
from jaxvcm import _media as Md
from jaxvcm import _sampling as S
from jaxvcm._scene import Water
from jaxvcm._vec import Vec3

from .. import _oracles as O

N = 200_000
P_PASS = 1e-4
P_WRONG = 1e-6
F32 = np.float32


def uniforms(seed, k, n=N, dt=F32):
    rng = np.random.default_rng(seed)
    return [jnp.asarray(rng.random(n, dtype=dt)) for _ in range(k)]  # [0, 1) in dt


def stack(v: Vec3):
    return np.stack([np.asarray(c, np.float64) for c in v], -1)


# ---------------------------------------------------------------------------- direction bins
def theta_edges(nb, hemisphere):
    """cos(theta) bin edges, increasing, equal steps in theta (small solid angle near the
    poles where forward / backward peaked lobes concentrate)."""
    th = np.linspace(0.0, np.pi / 2 if hemisphere else np.pi, nb + 1)
    return np.sort(np.cos(th))


PHI_EDGES = np.linspace(0.0, 2 * np.pi, 25)


def direction_counts(dirs, z_edges, axis=2):
    """Histogram of unit directions in (cos theta about `axis`, phi): axis z (local frames)
    with phi = atan2(y, x), or axis y (world, y up) with phi = atan2(z, x)."""
    a1, a2 = {2: (0, 1), 1: (0, 2)}[axis]
    z = np.clip(dirs[:, axis], -1.0, 1.0)
    phi = np.mod(np.arctan2(dirs[:, a2], dirs[:, a1]), 2 * np.pi)
    h, _, _ = np.histogram2d(z, phi, bins=[z_edges, PHI_EDGES])
    return h


def direction_expected(pdf_dir, z_edges, n=N, nodes=8):
    """N * integral over each (cos theta, phi) bin of pdf_dir(z, phi) dz dphi."""
    return n * O.bin_integrals_2d(pdf_dir, z_edges, PHI_EDGES, nodes)


def sphere_integral(pdf_dir):
    """Integral of pdf over the sphere: composite GL, 400 panels in cos theta (a panel edge at
    z = 0 for the hemisphere kink), 16 panels in phi, 16 nodes each."""
    z_edges = np.linspace(-1.0, 1.0, 401)
    phi_edges = np.linspace(0.0, 2 * np.pi, 17)
    return float(np.sum(O.bin_integrals_2d(pdf_dir, z_edges, phi_edges, 16)))


def np_pdf(fn):
    """Package pdf of mu, called in float64, as a function of (z, phi)."""
    def pdf(z, phi):
        return np.asarray(fn(jnp.asarray(z, jnp.float64)), np.float64) * np.ones_like(phi)
    return pdf


# direction samplers: name -> (sampler(u1, u2) -> Vec3, pdf(mu) float64, hemisphere?)
HG_G = (-0.7, 0.0, 0.3, 0.9)
WATER_B = 0.835
DIRECTIONAL = {
    "cosine_hemisphere": (S.cosine_hemisphere, S.cosine_hemisphere_pdf, True),
    "uniform_sphere": (S.uniform_sphere, lambda mu: jnp.full_like(mu, S.uniform_sphere_pdf()),
                       False),
    **{f"hg_g={g}": (lambda u1, u2, g=g: S.hg_sample(u1, u2, g),
                     lambda mu, g=g: S.hg_pdf(mu, g), False) for g in HG_G},
    "isotropic": (S.isotropic_sample, lambda mu: jnp.full_like(mu, S.INV_4PI), False),
    f"water_b={WATER_B}": (lambda u1, u2: S.water_phase_sample(u1, u2, WATER_B),
                           lambda mu: S.water_phase_pdf(mu, WATER_B), False),
}


def draw_directions(name, seed=0):
    sampler, _, _ = DIRECTIONAL[name]
    u1, u2 = uniforms(seed, 2)
    v = sampler(u1, u2)
    assert v.x.dtype == F32 and v.x.shape == (N,)
    return stack(v)


@pytest.mark.parametrize("name", list(DIRECTIONAL))
def test_direction_pdf_normalised(name):
    _, pdf, _ = DIRECTIONAL[name]
    np.testing.assert_allclose(sphere_integral(np_pdf(pdf)), 1.0, atol=1e-6)


@pytest.mark.parametrize("name", list(DIRECTIONAL))
def test_direction_sampler_chi2(name):
    _, pdf, hemi = DIRECTIONAL[name]
    dirs = draw_directions(name)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-5)  # unit vectors
    if hemi:
        assert np.all(dirs[:, 2] >= 0)
    z_edges = theta_edges(36, hemi)
    obs = direction_counts(dirs, z_edges)
    exp = direction_expected(np_pdf(pdf), z_edges)
    np.testing.assert_allclose(exp.sum(), N, rtol=1e-6)
    stat, dof, p = O.chi2_gof(obs, exp)
    assert p > P_PASS, f"{name}: chi2 = {stat:.1f} with {dof} dof, p = {p:.3g}"


@pytest.mark.parametrize("g", HG_G)
def test_hg_mean_cosine_is_g(g):
    """A defining property of Henyey-Greenstein: E[mu] = g (4 standard errors)."""
    mu = draw_directions(f"hg_g={g}")[:, 2]
    assert abs(mu.mean() - g) < 4 * mu.std() / np.sqrt(N)


# deliberately wrong pdfs for a sampler: must be rejected
WRONG = {
    "cosine_vs_uniform_hemisphere": ("cosine_hemisphere",
                                     lambda mu: jnp.where(mu >= 0, 0.5 / jnp.pi, 0.0)),
    "hg0.3_vs_hg0.35": ("hg_g=0.3", lambda mu: S.hg_pdf(mu, 0.35)),
    "hg0.9_vs_hg0.85": ("hg_g=0.9", lambda mu: S.hg_pdf(mu, 0.85)),
    "water_vs_isotropic": (f"water_b={WATER_B}", lambda mu: jnp.full_like(mu, S.INV_4PI)),
    "hg-0.7_vs_hg0.7": ("hg_g=-0.7", lambda mu: S.hg_pdf(mu, 0.7)),
}


@pytest.mark.parametrize("case", list(WRONG))
def test_direction_chi2_rejects_wrong_pdf(case):
    name, wrong = WRONG[case]
    hemi = DIRECTIONAL[name][2]
    z_edges = theta_edges(36, hemi)
    obs = direction_counts(draw_directions(name), z_edges)
    exp = direction_expected(np_pdf(wrong), z_edges)
    exp *= N / exp.sum()  # even a renormalised wrong shape must be rejected
    stat, dof, p = O.chi2_gof(obs, exp)
    assert p < P_WRONG, f"{case}: chi2 = {stat:.1f} with {dof} dof, p = {p:.3g} (not rejected)"


# ---------------------------------------------------------------------------- discrete
def test_sample_discrete():
    w = np.array([0.5, 0.0, 3.0, 1.25, 0.25, 2.0, 0.0], F32)
    (u,) = uniforms(7, 1)
    i, prob = jax.jit(jax.vmap(S.sample_discrete, in_axes=(None, 0)))(jnp.asarray(w), u)
    i, prob = np.asarray(i), np.asarray(prob)
    assert i.dtype == np.int32 and prob.dtype == F32
    assert np.all((i >= 0) & (i < len(w)))
    np.testing.assert_allclose(prob, w[i] / w.sum(), rtol=1e-6)
    assert np.all(w[i] > 0), "a zero-weight entry was chosen"
    obs = np.bincount(i, minlength=len(w))
    pmf = w.astype(np.float64) / w.sum()
    np.testing.assert_allclose(pmf.sum(), 1.0)
    stat, dof, p = O.chi2_gof(obs, N * pmf)
    assert p > P_PASS, f"chi2 = {stat:.1f} with {dof} dof, p = {p:.3g}"
    # and a wrong pmf (weights shifted) is rejected
    wrong = np.array([0.5, 0.0, 2.9, 1.35, 0.25, 2.0, 0.0]) / 7.0
    assert O.chi2_gof(obs, N * wrong)[2] < P_WRONG
    # edge cases: u = 0 never picks a leading zero weight; the largest u < 1 picks the last > 0
    lo = S.sample_discrete(jnp.asarray([0.0, 1.0, 1.0], F32), jnp.asarray(0.0, F32))[0]
    u_max = jnp.asarray(np.nextafter(F32(1), F32(0)))
    hi = S.sample_discrete(jnp.asarray([1.0, 1.0, 0.0], F32), u_max)[0]
    assert int(lo) == 1 and int(hi) == 1


# ---------------------------------------------------------------------------- lights
CAMERA = {"position": [0.0, 0.0, 5.0], "target": [0.0, 0.0, 0.0], "fov": 40.0,
          "width": 8, "height": 8}
RECT_LIGHT = {"type": "rect", "center": [0.1, 1.0, -0.2], "normal": [0.25, -1.0, 0.15],
              "size": [1.2, 0.7], "radiance": [4.0, 3.0, 2.0]}
SKY_LIGHT = {"type": "sky", "radiance": [0.3, 0.4, 0.6]}
SUN_LIGHT = {"type": "sun", "direction": [0.3, -1.0, 0.2], "irradiance": 5.0}
# A shading point below the rectangle and well off its axis, so that d^2 / cos varies by a
# factor ~4 over the light and a pdf without the cosine or the distance would be rejected.
P_SHADE = np.array([0.9, 0.25, 0.4])

LIGHT_SCENES = {
    "rect": [RECT_LIGHT],
    "sky": [SKY_LIGHT],
    "rect+sky": [RECT_LIGHT, SKY_LIGHT],
}


# a non-emissive floor gives the scene finite bounds (the sun and sky selection weights
# use the area of the bounding disk); it plays no part in light sampling
FLOOR = {"type": "rect", "center": [0.0, -0.5, 0.0], "normal": [0.0, 1.0, 0.0], "size": [2.0, 2.0],
         "material": "grey"}


def light_scene(lights, dt, shapes=(FLOOR,)):
    doc = {"camera": CAMERA, "materials": {"grey": {"type": "diffuse"}}, "shapes": list(shapes),
           "lights": lights}
    return jaxvcm.scene_from_dict(doc, dtype=dt)


def draw_light_samples(scene, seed, n=N):
    dt = np.dtype(scene.bounds.dtype).type
    p = Vec3(*(jnp.asarray(c, dt) for c in P_SHADE))
    us, u1, u2 = uniforms(seed, 3, n, dt)
    f = jax.jit(jax.vmap(lambda a, b, c: Lt.sample_light(scene, p, a, b, c)))
    return f(us, u1, u2)


def rect_geometry(scene, k):
    """Float64 p0, e1, e2 and unit normal of the rectangle of light k (independent maths)."""
    r = scene.lights.shape[k]
    rects = scene.rects
    p0, e1, e2 = (np.asarray(a, np.float64)[r] for a in (rects.p0, rects.e1, rects.e2))
    return p0, e1, e2, O.unit(np.cross(e1, e2))


@jax.jit
def _pdf_surface(scene, lid, wo, n, dist):
    return jax.vmap(lambda wo, n, dist: Lt.emitted_surface(scene, lid, wo, n, dist)[1])(wo, n, dist)


@jax.jit
def _pdf_escape(scene, d):
    return jax.vmap(lambda d: Lt.emitted_escape(scene, d)[1])(d)


def vec64(a):
    return Vec3(*(jnp.asarray(a[..., i], jnp.float64) for i in range(3)))


def rect_pdf_area(scene64, k):
    """(u, v) -> the package's NEE solid-angle pdf (selection included) of the point
    p0 + u e1 + v e2 seen from P_SHADE, times the Jacobian cos_l area / d^2 (own maths):
    the pdf of (u, v), which integrates to the selection probability."""
    p0, e1, e2, nl = rect_geometry(scene64, k)
    area = np.linalg.norm(np.cross(e1, e2))

    def pdf(u, v):
        shape = u.shape
        q = p0 + u.reshape(-1, 1) * e1 + v.reshape(-1, 1) * e2
        dv = q - P_SHADE
        dist = np.linalg.norm(dv, axis=1)
        wi = dv / dist[:, None]
        cos_l = -(wi @ nl)
        pw = np.asarray(_pdf_surface(scene64, jnp.asarray(k, jnp.int32), vec64(-wi),
                                     vec64(np.tile(nl, (len(dist), 1))), jnp.asarray(dist)))
        return (pw * cos_l * area / dist**2).reshape(shape)

    return pdf


def sky_pdf_dir(scene64):
    """(y, phi) -> the package's sky pdf (selection included) of direction
    (sin cos phi, y, sin sin phi): y-up world, phi measured from +x towards +z."""
    def pdf(y, phi):
        s = np.sqrt(np.maximum(0.0, 1.0 - y * y))
        d = np.stack([s * np.cos(phi), y, s * np.sin(phi)], -1).reshape(-1, 3)
        return np.asarray(_pdf_escape(scene64, vec64(d))).reshape(y.shape)
    return pdf


UV_EDGES = np.linspace(0.0, 1.0, 17)
SKY_Y_EDGES = theta_edges(18, True)


def light_histograms(scene32, ls):
    """Observed counts per light technique: rect samples in (u, v) of the light (found by
    intersecting the sampled ray with the rectangle), sky samples in (y, phi)."""
    wi = stack(ls.wi)
    dist = np.asarray(ls.dist, np.float64)
    out = {}
    for k, kind in enumerate(scene32.lights.kind):
        if kind == 0:  # rect
            sel = np.isfinite(dist)
            p0, e1, e2, _ = rect_geometry(scene32, k)
            n = int(sel.sum())
            _, u, v, _ = O.ref_parallelogram(np.tile(P_SHADE, (n, 1)), wi[sel], np.tile(p0, (n, 1)),
                                             np.tile(e1, (n, 1)), np.tile(e2, (n, 1)), tmin=-np.inf)
            # the sampled point reproduces the (u, v) up to float32 rounding
            h, _, _ = np.histogram2d(np.clip(u, 0, 1), np.clip(v, 0, 1), bins=[UV_EDGES, UV_EDGES])
            out[k] = h
        elif kind == 3:  # sky
            sel = ~np.isfinite(dist)
            out[k] = direction_counts(wi[sel], SKY_Y_EDGES, axis=1)
    return out


def light_expected(scene64, n=N):
    exp = {}
    for k, kind in enumerate(scene64.lights.kind):
        if kind == 0:
            exp[k] = n * O.bin_integrals_2d(rect_pdf_area(scene64, k), UV_EDGES, UV_EDGES, 6)
        elif kind == 3:
            exp[k] = n * O.bin_integrals_2d(sky_pdf_dir(scene64), SKY_Y_EDGES, PHI_EDGES, 6)
    return exp


@pytest.mark.parametrize("lights", list(LIGHT_SCENES))
def test_light_pdf_normalised(lights):
    """The solid-angle pdfs of all lights, selection included, integrate to one."""
    scene64 = light_scene(LIGHT_SCENES[lights], np.float64)
    total = 0.0
    for k, kind in enumerate(scene64.lights.kind):
        if kind == 0:
            edges = np.linspace(0, 1, 9)
            total += float(np.sum(O.bin_integrals_2d(rect_pdf_area(scene64, k), edges, edges, 12)))
        else:
            total += float(np.sum(O.bin_integrals_2d(sky_pdf_dir(scene64), np.linspace(0, 1, 201),
                                                     np.linspace(0, 2 * np.pi, 17), 16)))
    np.testing.assert_allclose(total, 1.0, atol=1e-6)


@pytest.mark.parametrize("lights", list(LIGHT_SCENES))
def test_light_sampler_chi2(lights):
    scene32 = light_scene(LIGHT_SCENES[lights], F32)
    scene64 = light_scene(LIGHT_SCENES[lights], np.float64)
    ls = draw_light_samples(scene32, seed=11)
    assert np.all(np.asarray(ls.valid)) and not np.any(np.asarray(ls.delta))
    wi = stack(ls.wi)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-5)
    # the sample's pdf_w is the pdf the integrator's MIS uses at an emitter hit / escape
    dist = np.asarray(ls.dist, np.float64)
    fin = np.isfinite(dist)
    pw = np.asarray(ls.pdf_w, np.float64)
    want = np.zeros(N)
    if fin.any():
        k = int(np.flatnonzero(np.array(scene64.lights.kind) == 0)[0])
        nl = rect_geometry(scene64, k)[3]
        want[fin] = np.asarray(_pdf_surface(
            scene64, jnp.asarray(k, jnp.int32), vec64(-wi[fin]),
            vec64(np.tile(nl, (fin.sum(), 1))), jnp.asarray(dist[fin])))
    if (~fin).any():
        want[~fin] = np.asarray(_pdf_escape(scene64, vec64(wi[~fin])))
    np.testing.assert_allclose(pw, want, rtol=2e-5)
    obs = light_histograms(scene32, ls)
    exp = light_expected(scene64)
    np.testing.assert_allclose(sum(e.sum() for e in exp.values()), N, rtol=1e-6)
    stat, dof, p = O.chi2_gof(np.concatenate([obs[k].ravel() for k in sorted(obs)]),
                              np.concatenate([exp[k].ravel() for k in sorted(exp)]))
    assert p > P_PASS, f"{lights}: chi2 = {stat:.1f} with {dof} dof, p = {p:.3g}"


def test_rect_light_chi2_rejects_pdf_without_cosine():
    """The rect-light expected counts built from d^2 / area (cosine forgotten) must fail."""
    scene32 = light_scene([RECT_LIGHT], F32)
    scene64 = light_scene([RECT_LIGHT], np.float64)
    obs = light_histograms(scene32, draw_light_samples(scene32, seed=11))[0]
    good = rect_pdf_area(scene64, 0)
    p0, e1, e2, nl = rect_geometry(scene64, 0)

    def wrong(u, v):
        q = p0 + u[..., None] * e1 + v[..., None] * e2
        dv = q - P_SHADE
        cos_l = -(dv @ nl) / np.linalg.norm(dv, axis=-1)
        return good(u, v) / cos_l  # as if the pdf lacked the 1 / cos_l

    exp = N * O.bin_integrals_2d(wrong, UV_EDGES, UV_EDGES, 6)
    exp *= N / exp.sum()
    assert O.chi2_gof(obs, exp)[2] < P_WRONG


def test_sun_light():
    """The sun is a delta light: wi = -direction exactly, pdf_w = its selection probability,
    dist = inf, delta; it is chosen with that probability (against a sky)."""
    scene = light_scene([SUN_LIGHT, SKY_LIGHT], F32)
    ls = draw_light_samples(scene, seed=5)
    sel = np.asarray(Lt.selection_pdf(scene), np.float64)
    np.testing.assert_allclose(sel.sum(), 1.0, rtol=1e-6)
    delta = np.asarray(ls.delta)
    wi = stack(ls.wi)
    dl = np.asarray(scene.lights.direction, np.float64)[0]
    np.testing.assert_allclose(dl, O.unit(np.array(SUN_LIGHT["direction"])), atol=1e-7)
    assert np.all(wi[delta] == -dl)  # exactly, in float32
    np.testing.assert_allclose(np.asarray(ls.pdf_w, np.float64)[delta], sel[0], rtol=1e-6)
    assert np.all(~np.isfinite(np.asarray(ls.dist)[delta])) and np.all(np.asarray(ls.valid)[delta])
    Le_sun = np.asarray(scene.lights.radiance)[0]
    np.testing.assert_array_equal(np.asarray(ls.Le)[delta], np.tile(Le_sun, (delta.sum(), 1)))
    # selection frequency: binomial, 4 standard errors
    frac = delta.mean()
    assert abs(frac - sel[0]) < 4 * np.sqrt(sel[0] * (1 - sel[0]) / N), (frac, sel[0])
    # the non-delta samples are the sky's, with its pdf times its selection probability
    y = wi[~delta, 1]
    np.testing.assert_allclose(np.asarray(ls.pdf_w, np.float64)[~delta], y / np.pi * sel[1],
                               rtol=2e-5)


@pytest.mark.parametrize("lights", [[SKY_LIGHT], [SUN_LIGHT], [SUN_LIGHT, SKY_LIGHT]],
                         ids=["sky", "sun", "sun+sky"])
def test_light_selection_without_geometry(lights):
    """A scene whose only lights are sun / sky and that has no geometry loads fine, so its
    light selection must still be a probability distribution (not 0 / 0)."""
    scene = light_scene(lights, F32, shapes=())
    sel = np.asarray(Lt.selection_pdf(scene), np.float64)
    pw = np.asarray(scene.lights.power_weight)
    assert np.all(np.isfinite(sel)), f"selection pdf {sel} (power weights {pw})"
    np.testing.assert_allclose(sel.sum(), 1.0, rtol=1e-6)
    ls = draw_light_samples(scene, seed=1, n=64)
    assert np.all(np.isfinite(np.asarray(ls.pdf_w)) & (np.asarray(ls.pdf_w) > 0))


# ---------------------------------------------------------------------------- free flight
SIGMA_S = (0.5, 1.0, 2.0)
SIGMA_A = (0.2, 0.05, 0.4)
T_SURF = 1.5
T_EDGES = np.linspace(0.0, T_SURF, 31)


def make_water(dt, sigma_s=SIGMA_S, sigma_a=SIGMA_A):
    A = lambda x: jnp.asarray(np.asarray(x, np.float64), dt)  # noqa: E731
    return Water(enabled=True, phase_kind=0, level=A(0.0), amp=A(np.zeros(0)), kx=A(np.zeros(0)),
                 kz=A(np.zeros(0)), phase0=A(np.zeros(0)), footprint=A([-1, 1, -1, 1]),
                 floor=A(-1.0),
                 sigma_a=A(sigma_a), sigma_s=A(sigma_s), g=A(0.0), b=A(0.835), ior=A(1.33), mat=0)


def draw_flights(dt, seed=3):
    w = make_water(dt)
    u_ch, u_t = uniforms(seed, 2, N, dt)
    f = jax.jit(jax.vmap(lambda a, b: Md.sample_free_flight(w, jnp.asarray(T_SURF, dt), a, b)))
    return f(u_ch, u_t)


def scatter_pdf64(sigma_s=SIGMA_S):
    """The package's scatter_pdf in float64 as a vectorised function of t (vmapped over
    scalar t, the per-ray form)."""
    s = jnp.asarray(sigma_s, jnp.float64)
    f = jax.jit(jax.vmap(lambda t: Md.scatter_pdf(s, t)))

    def pdf(t):
        t = np.asarray(t, np.float64)
        return np.asarray(f(jnp.asarray(t.ravel()))).reshape(t.shape)
    return pdf


def pass_prob64(t, sigma_s=SIGMA_S):
    return float(Md.pass_prob(jnp.asarray(sigma_s, jnp.float64), jnp.asarray(t, jnp.float64)))


def test_free_flight_pdf_normalised():
    pdf = scatter_pdf64()
    # all of [0, inf): exp(-0.5 * 80) = 4e-18
    whole = float(np.sum(O.bin_integrals_1d(pdf, np.linspace(0, 80, 801))))
    np.testing.assert_allclose(whole, 1.0, atol=1e-9)
    # scatter before the surface + pass = 1, and pass_prob is the tail of scatter_pdf
    before = float(np.sum(O.bin_integrals_1d(pdf, T_EDGES)))
    np.testing.assert_allclose(before + pass_prob64(T_SURF), 1.0, atol=1e-9)
    np.testing.assert_allclose(pass_prob64(T_SURF), np.mean(np.exp(-np.array(SIGMA_S) * T_SURF)),
                               rtol=1e-12)


def flight_counts(ff):
    t = np.asarray(ff.t, np.float64)
    sc = np.asarray(ff.scatter)
    h, _ = np.histogram(t[sc], bins=T_EDGES)
    return np.append(h, (~sc).sum())


def test_free_flight_distances_chi2():
    ff = draw_flights(F32)
    t, sc = np.asarray(ff.t, np.float64), np.asarray(ff.scatter)
    assert np.all(t[sc] < T_SURF) and np.all(t[~sc] == F32(T_SURF))
    # the reported pdf is the mixture pdf at a scatter, the pass probability otherwise
    np.testing.assert_allclose(np.asarray(ff.pdf, np.float64)[sc], scatter_pdf64()(t[sc]),
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(ff.pdf, np.float64)[~sc], pass_prob64(T_SURF), rtol=1e-5)
    obs = flight_counts(ff)
    exp = N * np.append(O.bin_integrals_1d(scatter_pdf64(), T_EDGES), pass_prob64(T_SURF))
    stat, dof, p = O.chi2_gof(obs, exp)
    assert p > P_PASS, f"chi2 = {stat:.1f} with {dof} dof, p = {p:.3g}"
    # pass fraction: binomial, 4 standard errors
    pp = pass_prob64(T_SURF)
    assert abs((~sc).mean() - pp) < 4 * np.sqrt(pp * (1 - pp) / N)
    # power: the single-channel pdf (channel 0 only) is rejected
    wrong = N * np.append(O.bin_integrals_1d(scatter_pdf64((0.5,)), T_EDGES),
                          pass_prob64(T_SURF, (0.5,)))
    assert O.chi2_gof(obs, wrong)[2] < P_WRONG


@pytest.mark.parametrize("dt", [pytest.param(np.float32, id="float32"),
                                pytest.param(np.float64, id="float64")])
def test_free_flight_weight_unbiased(dt):
    """E[weight_c] = int_0^T sigma_s,c exp(-sigma_t,c t) dt + exp(-sigma_t,c T) per channel:
    the scattered mass before the surface plus the transmittance to it."""
    ff = draw_flights(dt, seed=4)
    w = np.asarray(ff.weight, np.float64)
    assert w.shape == (N, 3) and ff.weight.dtype == dt and np.all(np.isfinite(w))
    ss, st = np.array(SIGMA_S), np.array(SIGMA_S) + np.array(SIGMA_A)
    want = ss / st * (1 - np.exp(-st * T_SURF)) + np.exp(-st * T_SURF)
    mean, se = w.mean(0), w.std(0) / np.sqrt(N)
    assert np.all(np.abs(mean - want) < 4 * se), (mean, want, se)
