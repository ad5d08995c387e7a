"""The glint technique (`jaxvcm._glints`): the lights seen in the water surface from the
pinhole, by a manifold connection per camera path, MIS-weighted against the emitter hits.

Closed forms (flat water: the surface is a plane mirror):
  * a point light of intensity I at y: its mirror image y' = (y.x, 2 level - y.y, y.z)
    at distance D from the pinhole c; the pixel that holds the direction c -> y' gets
    W(w) R(theta) I / D^2 (the irradiance R I / D^2 across the ray, times the pixel's
    importance W = 1 / (A_pix cos^3)), every other pixel 0;
  * the sun of irradiance E travelling along d: the mirror keeps the beam's section, so
    the pixel of the direction -(d.x, -d.y, d.z) gets W(w) R(theta) E.
Unbiasedness: PT with glints against PT without (the same camera paths, an independent
glint sample each) on a pool whose light is large enough for the emitter hits alone to
converge; a planted mistake (the emitter hits keep their full weight) must fail.
Weights: on paths the solver returns, w_g + w_eh = 1 (glint weight from the glint side,
emitter-hit share recomputed at the emitter hit from its own vertices).
Gradients: with respect to a wave's amplitude (through the root's implicit function) and
the light's intensity, against central finite differences.
"""

from __future__ import annotations

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import Technique
from jaxvcm import _glints as glints
from jaxvcm import _manifold as manifold
from jaxvcm._vec import Vec3
from tests import _oracles as O
from tests._scenes import shipped_doc

GLINT = Technique("glint", 1, 1)
EH = Technique("connection", 0, 3)  # pinhole -> water surface -> light
N = 24  # image side


def _pool(**over):
    return jaxvcm.scene_from_dict(shipped_doc("pool", N, N, **over), "pool")


def _images(scene, cfg, keys):
    # lax.map, not vmap (as tests/_analytic.py): under vmap the work queues' skips become
    # selects, and the glints' queued solves ran for every lane (64 passes: 173 s vs 26 s)
    f = jax.jit(lambda ks: jax.lax.map(
        lambda k: jaxvcm.technique_images(scene, k, cfg, 0)[0].images, ks))
    return np.asarray(f(keys))


def _labels(scene, cfg):
    return jax.eval_shape(lambda k: jaxvcm.technique_images(scene, k, cfg, 0)[0],
                          jax.random.key(0)).labels


def _film_xy(scene, w):
    """(px, py, cos): where the unit direction w leaving the pinhole meets the film, in
    pixels (NumPy, from the camera's definition: the film at distance 1)."""
    cam = scene.camera
    f, r, u = (np.asarray(a, float) for a in (cam.forward, cam.right, cam.up))
    t = float(cam.tan_half_fov)
    aspect = cam.width / cam.height
    cos = w @ f
    px = (w @ r / cos / (aspect * t) + 1) * 0.5 * cam.width
    py = (1 - w @ u / cos / t) * 0.5 * cam.height
    return px, py, cos


def _pixel_of(scene, w):
    """(pixel index, W) of the unit direction w leaving the pinhole: pixels of area
    A_pix, importance W = 1 / (A_pix cos^3)."""
    cam = scene.camera
    px, py, cos = _film_xy(scene, w)
    t = float(cam.tan_half_fov)
    a_pix = (2 * t * cam.width / cam.height / cam.width) * (2 * t / cam.height)
    return int(py) * cam.width + int(px), 1.0 / (a_pix * cos**3)


# ---------------------------------------------------------------- closed forms
def _glint_stage(scene, cfg, keys):
    """The glint technique's image [K, H, W, C] of one sample per pixel, per key."""
    pix = jnp.arange(N * N, dtype=jnp.int32)
    # one light point per path: each pixel's value is then 0 or one light's closed form
    f = jax.jit(jax.vmap(lambda sc, k: glints.glints(sc, cfg, pix, k, samples=1)[0],
                         in_axes=(None, 0)))
    return np.asarray(f(scene, keys))


def _refracted_point(c, y, eta):
    """Flat water at level 0, pinhole c under it, point y above: (unit direction from c
    to the refraction point, cos theta_air, cos theta_water, d omega_y / d A_perp(c)).
    rho(theta_a) = H tan theta_a + D tan theta_w (sin theta_a = eta sin theta_w) is the
    horizontal distance a ray leaving y at theta_a lands from y's foot at c's depth;
    d omega = sin theta_a d theta_a d phi, d A = rho d rho d phi, d A_perp = d A cos theta_w."""
    from scipy.optimize import brentq

    H, D = y[1], -c[1]
    h = np.array([c[0] - y[0], 0.0, c[2] - y[2]])
    P = np.linalg.norm(h)

    def rho(ta):
        tw = np.arcsin(np.sin(ta) / eta)
        return H * np.tan(ta) + D * np.tan(tw)

    ta = brentq(lambda t: rho(t) - P, 0.0, 1.2)
    tw = np.arcsin(np.sin(ta) / eta)
    drho = H / np.cos(ta) ** 2 + D / np.cos(tw) ** 2 * np.cos(ta) / (eta * np.cos(tw))
    dw_dA = np.sin(ta) / (P * drho * np.cos(tw))
    w = -h / P * np.sin(tw) + np.array([0.0, np.cos(tw), 0.0])  # up and towards y's foot
    return w, np.cos(ta), np.cos(tw), dw_dA


@pytest.mark.parametrize("view", ["above", "under"])
def test_flat_water_glint_closed_form(view):
    # flat water at level 0 under a point light and the sun: each pixel's sample picks one
    # of them (p_sel) and its glint is deterministic (w_g = 1: no camera ray hits a point
    # light or the sun), so the glint pixel of light k holds 0 or its closed form / p_sel_k
    # and every other pixel 0. above: the mirror images; under: the camera 0.6 m under the
    # water sees both through the surface (Fresnel T, the water's transmittance along the
    # ray, no n^2 factor: these are irradiances, _refracted_point)
    y = np.array([0.25, 3.0, -0.25])
    d = np.array([0.1, -4.7, 1.5]) / np.linalg.norm([0.1, -4.7, 1.5])
    over = {}
    if view == "under":
        over["camera"] = {"position": [0.1, -0.6, 0.2], "target": [0.2, 0.0, 0.05],
                          "up": [0.0, 0.0, -1.0], "fov": 60.0, "width": N, "height": N}
    scene = _pool(water__waves=[], lights=[
        {"type": "point", "position": list(y), "intensity": 40.0},
        {"type": "sun", "direction": list(d), "irradiance": 5.0}], **over)
    cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2, glints=True)
    imgs = _glint_stage(scene, cfg, jax.random.split(jax.random.key(1), 16)).reshape(16, N * N, 3)
    c = np.asarray(scene.camera.origin, float)
    eta = 1.33
    sig_t = np.asarray(scene.water.sigma_a, float) + np.asarray(scene.water.sigma_s, float)
    if view == "above":
        y_img = y * np.array([1, -1, 1])  # the point's mirror image in the plane y = 0
        D = np.linalg.norm(y_img - c)
        w_p, w_s = (y_img - c) / D, -d * np.array([1, -1, 1])
        # (direction from the pinhole, irradiance across the ray at the pinhole)
        forms = [(w_p, 40.0 / D**2 * jaxvcm.fresnel_unpolarised(abs(w_p[1]), eta)),
                 (w_s, 5.0 * jaxvcm.fresnel_unpolarised(abs(w_s[1]), eta))]
    else:
        w_p, ca, cw, dw_dA = _refracted_point(c, y, eta)
        T_p = 1.0 - jaxvcm.fresnel_unpolarised(ca, eta)
        ca_s = -d[1]
        cw_s = np.sqrt(1.0 - (1.0 - ca_s**2) / eta**2)
        h = np.array([d[0], 0.0, d[2]]) / np.hypot(d[0], d[2])
        w_s = -(h * np.sqrt(1.0 - cw_s**2) - np.array([0.0, cw_s, 0.0]))  # against the beam
        T_s = 1.0 - jaxvcm.fresnel_unpolarised(ca_s, eta)
        forms = [(w_p, 40.0 * T_p * dw_dA * np.exp(-sig_t * -c[1] / cw)),
                 (w_s, 5.0 * T_s * ca_s / cw_s * np.exp(-sig_t * -c[1] / cw_s))]
    sel = np.asarray(jaxvcm._lights.selection_pdf(scene))
    pixels, values = [], []
    # a root on a pixel's edge (to float32 rounding) is counted by whichever pixels round
    # it in: a well-posed closed form keeps each direction 1e-3 pixel from the edges (the
    # sun's mirror direction of (0.1, -4.7, 1.6) lies 2e-7 pixel from a row's edge)
    for w, _ in forms:
        assert min(abs(v - round(v)) for v in _film_xy(scene, w)[:2]) > 1e-3
    for k, (w, E) in enumerate(forms):
        pix, W = _pixel_of(scene, w)
        pixels.append(pix)
        values.append(W * E / sel[k])
    assert pixels[0] != pixels[1]
    others = np.ones(N * N, bool)
    others[pixels] = False
    assert not imgs[:, others].any()
    for pix, v in zip(pixels, values):
        got = imgs[:, pix, :]
        hit = got[:, 0] > 0
        assert 0 < hit.sum() < len(hit)  # the light was picked by some samples, not all
        np.testing.assert_allclose(got[hit], np.broadcast_to(v, got[hit].shape), rtol=2e-4)


# ---------------------------------------------------------------- light points
@pytest.mark.parametrize("samples", [1, 6, 8, 16])
def test_a_path_s_light_points_are_stratified_and_uniform_together(samples):
    # gx x gy strata over the light's two position uniforms (16 -> 4 x 4, 8 -> 2 x 4, 6 -> 2 x 3): every
    # path has one point in each stratum, uniform within it, so the n points together are
    # uniform on the unit square (each stratum has probability 1/n, and the mean of the n
    # values f / p is unbiased): the pooled mean of a uniform is 1/2 with standard error
    # sqrt(1/12 / (N n)) at most (stratified, it is smaller); the other three uniforms are
    # untouched, i.i.d. uniform per point
    gx, gy = glints.strata(samples)
    assert gx * gy == samples and gx <= gy and (samples != 8 or (gx, gy) == (2, 4))
    assert samples != 16 or (gx, gy) == (4, 4)
    N = 4096
    u = np.asarray(glints.light_uniforms(jax.random.key(1), N, samples, jnp.float32))
    u = u.reshape(N, samples, 5)
    assert u.min() >= 0.0 and u.max() <= 1.0
    cell = np.floor(u[..., 1] * gx).astype(int) + gx * np.floor(u[..., 2] * gy).astype(int)
    np.testing.assert_array_equal(np.sort(cell, axis=1), np.broadcast_to(np.arange(samples),
                                                                          (N, samples)))
    for c in range(5):  # the pooled points: uniform (mean 1/2, variance 1/12)
        x = u[..., c].ravel()
        assert abs(x.mean() - 0.5) < 4.0 * np.sqrt(1.0 / 12.0 / x.size)
        assert abs(x.var() - 1.0 / 12.0) < 0.005
        # 10 bins of equal count within 4 standard errors (a stratum left out would empty
        # whole bins)
        h = np.histogram(x, bins=10, range=(0.0, 1.0))[0] / x.size
        assert np.all(np.abs(h - 0.1) < 4.0 * np.sqrt(0.1 * 0.9 / x.size))
    for c in (0, 3, 4):  # the uniforms that do not place the point: uniform per point
        for k in range(samples):
            x = u[:, k, c]
            assert abs(x.mean() - 0.5) < 4.0 * np.sqrt(1.0 / 12.0 / N)
    # planted mistake: independent points leave some path's strata empty
    v = np.asarray(jax.random.uniform(jax.random.key(1), (N, samples, 5)))
    cell = np.floor(v[..., 1] * gx).astype(int) + gx * np.floor(v[..., 2] * gy).astype(int)
    assert samples == 1 or np.any(np.sort(cell, axis=1) != np.arange(samples))


# ---------------------------------------------------------------- MIS weights
def test_weights_sum_to_one_on_the_paths_the_solver_returns():
    # random light points y of the shipped pool's light, each pixel's root F_j(y) (the
    # glint side); at the emitter hit of the same path (z1 = the root, z2 = y) the share
    # is recomputed from those vertices alone: w_g + w_eh = 1 on every returned path
    scene = jaxvcm.load_scene("scenes/pool.toml", width=96, height=96)
    cfg = jaxvcm.RenderConfig(algorithm="vcm", glints=True)
    rng = np.random.default_rng(3)
    f32 = np.float32
    c0 = np.asarray(scene.camera.origin)
    # the pairs (pixel, y) that hold a root: every root of 48 light points (the full
    # search: a 40 x 40 seed grid over the pool) and the pixel its direction falls in
    ys = np.stack([0.25 + rng.uniform(-0.075, 0.075, 48), np.full(48, 3.0),
                   -0.25 + rng.uniform(-0.075, 0.075, 48)], 1).astype(f32)
    sol = jax.jit(jax.vmap(lambda b: manifold.solve(
        scene.water, Vec3(*(jnp.asarray(v, f32) for v in c0)), b, refract=False, capacity=48,
        grid=40)))(Vec3(*(jnp.asarray(ys[:, i]) for i in range(3))))
    roots = np.stack([np.asarray(a) for a in sol.s], -1)  # [48, K, 3]
    valid = np.asarray(sol.valid)
    pairs = []
    for i, k in zip(*np.nonzero(valid)):
        w = roots[i, k] - c0
        p, _ = _pixel_of(scene, w / np.linalg.norm(w))
        if 0 <= p < 96 * 96:
            pairs.append((p, i, k))
    M = len(pairs)
    pix = jnp.asarray([p for p, _, _ in pairs], jnp.int32)
    yy = ys[[i for _, i, _ in pairs]]
    y = Vec3(*(jnp.asarray(yy[:, i]) for i in range(3)))
    rr = np.stack([roots[i, k] for _, i, k in pairs]).astype(f32)
    root = Vec3(*(jnp.asarray(rr[:, i]) for i in range(3)))
    n_y = Vec3(jnp.zeros(M, f32), -jnp.ones(M, f32), jnp.zeros(M, f32))
    c = Vec3(*(jnp.full(M, v, f32) for v in c0))
    light = jnp.zeros(M, jnp.int32)

    def one(p, c, y, root, n_y, light, shift):
        ok, s = glints.roots(scene, p, c, y, jnp.asarray(False), jnp.asarray(True))
        d = jnp.sqrt((s.x - root.x) ** 2 + (s.y - root.y) ** 2 + (s.z - root.z) ** 2)
        found = jnp.any(ok & (d < 1e-4))  # F_j(y) holds this root
        n_found = jnp.sum(ok)
        p_eh = glints.emitter_pdf(scene, c, root, y, n_y, False)
        p_g = jaxvcm._lights.light_point_pdf(scene, light, y)
        w_g = glints.glint_weight(cfg, p_g, p_eh)
        z1 = jaxvcm._subpath.PathEnds(*([None] * 16))._replace(
            p=root + Vec3(shift, 0.0 * shift, 0.0 * shift), kind=jnp.int32(1),
            mat=jnp.int32(scene.water.mat))
        z2 = z1._replace(p=y, n=n_y)
        w_eh = glints.emitter_share(scene, cfg, c, z1, z2, light, jnp.asarray(False), 2, p)
        return found, n_found, w_g, w_eh

    args = (pix, c, y, root, n_y, light)
    found, n_found, w_g, w_eh = (np.asarray(a) for a in jax.jit(jax.vmap(one))(
        *args, jnp.zeros(M, f32)))
    assert M > 500
    # the pixel's seeds return every root that lies in the pixel, the pairs of two roots in
    # one pixel (a fold of the glint) included (one seed per pixel: 99.3 % of them)
    assert found.mean() == 1.0
    shared = collections.Counter((p, i) for p, i, _ in pairs)
    assert any(n > 1 for n in shared.values())  # such pairs are among these roots
    # ... and no root twice: as many as the full search holds in the pixel
    np.testing.assert_array_equal(n_found, [shared[(p, i)] for p, i, _ in pairs])
    # both heuristics' weights come from the same pdfs: the sum is 1 to float32 rounding
    # (p_eh at the full search's root and at the pixel's own, equal to the rounding of a
    # position, which the chain's Jacobian amplifies a few times)
    np.testing.assert_allclose((w_g + w_eh)[found], 1.0, atol=1e-5)
    # the cull before the solves (`_may_hold`) kept every pixel above that holds a root,
    # and drops most (pixel, point) pairs: a pixel's surface can only tilt so far
    F = jnp.asarray(False)
    may = jax.jit(jax.vmap(lambda b: jax.vmap(lambda p: glints._may_hold(
        scene, p, Vec3(*(jnp.asarray(v, f32) for v in c0)), b, F, False))(
        jnp.arange(96 * 96, dtype=jnp.int32))))(Vec3(*(jnp.asarray(ys[:, i]) for i in range(3))))
    may = np.asarray(may)
    assert may[[i for _, i, _ in pairs], [p for p, _, _ in pairs]].all()
    assert may.mean() < 0.25  # 17.7 %
    # planted mistake: the region of the pixel two to the side drops some of the roots
    # (11 %; the next pixel's still holds them all: the bound's margins reach that far)
    assert not may[[i for _, i, _ in pairs], [(p + 2) % (96 * 96) for p, _, _ in pairs]].all()
    # both techniques take part; at this size the glint's pdf dominates (a pixel's footprint
    # reflects a region of the light's plane far larger than the light)
    assert np.all(w_eh[found] > 0) and np.mean(w_g[found]) > 0.5
    # planted mistake: an emitter hit 1 mm off the root is another path (a different
    # z1): the share must not be taken, so the pair no longer sums to 1
    _, _, w_g2, w_eh2 = (np.asarray(a) for a in jax.jit(jax.vmap(one))(
        *args, jnp.full(M, 1e-3, f32)))
    assert np.all(w_eh2 == 1.0)
    assert np.all((w_g2 + w_eh2)[found] > 1.0 + 1e-3)


# ---------------------------------------------------------------- unbiasedness
def _first_water_hit(waves, level, o, d, t0, t1, steps=256):
    """First crossing of the heightfield by rays o + t d, t in [t0, t1] ([n] each): a dense
    march (the slab's rays cross at most a few cm of it here) and bisection, float64."""
    ts = t0[:, None] + (t1 - t0)[:, None] * np.linspace(0.0, 1.0, steps)[None]
    p = o[:, None] + ts[..., None] * d[:, None]
    f = p[..., 1] - O.water_h(waves, level, p[..., 0], p[..., 2])
    below = f <= 0
    hit = below.any(axis=1)
    i = np.argmax(below, axis=1)
    lo = ts[np.arange(len(ts)), np.maximum(i - 1, 0)]
    hi = ts[np.arange(len(ts)), i]
    for _ in range(60):
        m = 0.5 * (lo + hi)
        q = o + m[:, None] * d
        fm = q[:, 1] - O.water_h(waves, level, q[:, 0], q[:, 2])
        lo, hi = np.where(fm > 0, m, lo), np.where(fm > 0, hi, m)
    return np.where(hit, hi, np.inf)


def _reflection_oracle(scene, Le, lo, hi, sub=4, fine=48):
    """float64 NumPy image [H, W] of the light reflected once by the water surface into the
    pinhole: stratified rays per pixel, each R(theta) Le where its reflection reaches the
    rect light's emitting face unoccluded (walls black: a ray that meets a wall first
    carries nothing), 0 elsewhere. sub x sub rays in every pixel, then fine x fine in the
    pixels that saw light and their neighbours (the glints' edges)."""
    cam = scene.camera
    W, H = cam.width, cam.height
    coarse = _reflected(scene, Le, lo, hi, np.arange(W * H), sub)
    lit = (coarse > 0).reshape(H, W)
    near = lit.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= np.roll(np.roll(lit, dy, 0), dx, 1)
    out = np.zeros(W * H)
    idx = np.flatnonzero(near)
    out[idx] = _reflected(scene, Le, lo, hi, idx, fine)
    return out.reshape(H, W)


def _reflected(scene, Le, lo, hi, pixels, sub):
    """The mean over sub x sub stratified rays of each pixel in `pixels` (row-major)."""
    cam = scene.camera
    W, H = cam.width, cam.height
    f, r, u = (np.asarray(a, float) for a in (cam.forward, cam.right, cam.up))
    c = np.asarray(cam.origin, float)
    t = float(cam.tan_half_fov)
    g = (np.arange(sub) + 0.5) / sub
    gx, gy = np.meshgrid(g, g)
    PX = (pixels % W)[:, None] + gx.ravel()[None]  # [n, sub^2]
    PY = (pixels // W)[:, None] + gy.ravel()[None]
    sx = (2 * PX / W - 1) * (W / H) * t
    sy = (1 - 2 * PY / H) * t
    d = O.unit(f + sx[..., None] * r + sy[..., None] * u).reshape(-1, 3)
    o = np.broadcast_to(c, d.shape)
    waves, level = O.waves_of(scene.water), float(scene.water.level)
    amp = np.abs(waves[:, 0]).sum()
    tops = [hi[1]] * 4
    faces = O.basin_faces(lo, hi, tops)
    # camera ray: into the slab of the waves, first surface crossing before any wall
    t0 = (level + amp - c[1]) / d[:, 1]
    t1 = (level - amp - c[1]) / d[:, 1]
    tw = _first_water_hit(waves, level, o, d, t0, t1)
    tb = O.ref_basin(o, d, faces)[0]
    s = o + tw[:, None] * d
    fp = np.asarray(scene.water.footprint, float)
    ok = np.isfinite(tw) & (tw < tb) & (s[:, 0] > fp[0]) & (s[:, 0] < fp[1]) & (
        s[:, 2] > fp[2]) & (s[:, 2] < fp[3])
    k = int(scene.lights.shape[0])  # the light's rect (it also blocks camera rays)
    p0, e1, e2 = (np.asarray(a[k], float) for a in (scene.rects.p0, scene.rects.e1,
                                                     scene.rects.e2))

    def on_rect(o, w):
        t = (p0[1] - o[:, 1]) / np.where(w[:, 1] != 0, w[:, 1], 1e-300)
        q = o + t[:, None] * w - p0
        a1, a2 = q @ e1 / (e1 @ e1), q @ e2 / (e2 @ e2)
        return (t > 0) & (a1 >= 0) & (a1 <= 1) & (a2 >= 0) & (a2 <= 1), t

    hit0, t0_l = on_rect(o, d)
    ok = ok & ~(hit0 & (t0_l < tw))
    n = O.heightfield_normal(waves, level, s[:, 0], s[:, 2])
    cos = -np.sum(d * n, axis=1)
    w = d + 2 * cos[:, None] * n  # mirror reflection
    # reflected ray: out of the slab without meeting the surface again, past the walls'
    # tops without meeting a wall, onto the light's plane inside the rect (normal -y)
    tout = np.maximum((level + amp - s[:, 1]) / np.maximum(w[:, 1], 1e-9), 0) + 1e-6
    again = np.isfinite(_first_water_hit(waves, level, s + 1e-7 * w, w, np.zeros(len(s)),
                                         tout, steps=64))
    tb2 = O.ref_basin(s + 1e-7 * w, w, faces)[0]
    hit1, t_l = on_rect(s, w)
    on = (w[:, 1] > 0) & hit1 & (t_l < tb2)
    R = jaxvcm.fresnel_unpolarised(np.clip(cos, 0, 1), float(scene.water.ior))
    val = np.where(ok & on & ~again, R * Le, 0.0)
    return val.reshape(len(pixels), sub * sub).mean(axis=1)


@pytest.fixture(scope="module")
def pool_runs():
    # the shipped pool and light with longer waves (wavelengths and amplitudes x 4: the
    # same slopes, one root per 8 cm pixel footprint), black walls and floor, PT to depth
    # 2: besides the light's direct view the only light is pinhole -> water surface ->
    # light (the emitter hits (0, 3) through the surface and the glints); glints on and
    # off, the same camera paths
    doc = shipped_doc("pool", N, N, materials__floor__albedo=0.0,
                      materials__wall__albedo=[0.0, 0.0, 0.0])
    doc["water"]["waves"] = [[4 * A, kx / 4, kz / 4, ph] for A, kx, kz, ph in
                             doc["water"]["waves"]]
    scene = jaxvcm.scene_from_dict(doc, "pool")
    keys = jax.random.split(jax.random.key(7), 64)
    out = {}
    for g in (False, True):
        cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2, glints=g)
        labels = _labels(scene, cfg)
        ims = _images(scene, cfg, keys)
        out[g] = {lab: ims[:, i] for i, lab in enumerate(labels)}
    basin = doc["shapes"][0]
    out["oracle"] = _reflection_oracle(scene, doc["lights"][0]["radiance"],
                                       np.array(basin["min"], float),
                                       np.array(basin["max"], float))
    return out


def test_glints_and_emitter_hits_against_reflection_oracle(pool_runs):
    # the oracle: 48 x 48 rays per lit pixel (from 32 x 32 to 64 x 64 its image mean moves
    # by 0.6 %: the 1 % allowance below)
    ref = pool_runs["oracle"]  # [H, W], every channel alike
    est = (pool_runs[True][EH] + pool_runs[True][GLINT]).mean(axis=-1)  # [P, H, W]
    P = len(est)
    tot = est.mean(axis=(1, 2))
    se = tot.std(ddof=1) / np.sqrt(P)
    # the bar can see a 5 % error at 4 standard errors
    assert 4 * se < 0.05 * ref.mean()
    assert abs(tot.mean() - ref.mean()) < 4 * se + 0.01 * ref.mean()
    # and pixel by pixel, where the oracle is lit
    m, s_px = est.mean(0), est.std(0, ddof=1) / np.sqrt(P)
    assert np.all(np.abs(m - ref) <= 4.5 * s_px + 0.03 * ref.max())
    # the emitter hits alone, on the same camera paths: a handful of hits in 64 passes at
    # most (what the glints are for): far off, or far noisier
    eh = pool_runs[False][EH].mean(axis=-1).mean(axis=(1, 2))
    assert abs(eh.mean() - ref.mean()) > 0.5 * ref.mean() or eh.std() > 5 * tot.std()


def test_glints_add_one_technique(pool_runs):
    # the glint technique is one more image beside the others (the film's sum), and the
    # emitter hits' other path lengths keep their values (only (0, 3) shares its paths)
    assert set(pool_runs[True]) == set(pool_runs[False]) | {GLINT}
    for lab in pool_runs[False]:
        if lab != EH:
            np.testing.assert_array_equal(pool_runs[True][lab], pool_runs[False][lab])


# ---------------------------------------------------------------- gradients
def test_gradients_through_the_root():
    # one small wave over otherwise flat water, a point light: the glint is a single
    # deterministic pixel whose value moves smoothly with the amplitude (the root by the
    # implicit function theorem, the Jacobian by its derivative); the intensity enters
    # linearly
    scene = _pool(water__waves=[[0.004, 3.0, 2.0, 0.4]],
                  lights=[{"type": "point", "position": [0.25, 3.0, -0.25], "intensity": 40.0}])
    cfg = jaxvcm.RenderConfig(algorithm="pt", max_depth=2, glints=True)
    key = jax.random.key(2)
    pix = jnp.arange(N * N, dtype=jnp.int32)

    def total(amp, inten):
        s = eqx.tree_at(lambda t: t.water.amp, scene, amp)
        s = eqx.tree_at(lambda t: t.lights.radiance, s, inten)
        return glints.glints(s, cfg, pix, key)[0].sum()

    amp0, i0 = scene.water.amp, scene.lights.radiance
    # one program for the gradient and the differences: its value is the forward pass
    vg = jax.jit(jax.value_and_grad(total, argnums=(0, 1)))

    def f(*args):
        return vg(*args)[0]

    g_amp, g_int = vg(amp0, i0)[1]
    h = 1e-4
    fd = (f(amp0 + h, i0) - f(amp0 - h, i0)) / (2 * h)
    assert float(f(amp0, i0)) > 0
    assert abs(float(fd)) > 1e-3 * float(f(amp0, i0)) / 0.004  # the amplitude matters
    np.testing.assert_allclose(float(g_amp[0]), float(fd), rtol=0.02)
    # linear in the intensity: sum_c I_c d total / d I_c = total
    np.testing.assert_allclose(float(jnp.sum(g_int * i0)), float(f(amp0, i0)), rtol=1e-4)


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize("alg", ["ppm", "lt"])
def test_glints_need_weighted_emitter_hits(alg):
    # ppm's emission along a delta prefix takes weight 1 and lt has no emitter hits:
    # nothing to share the glints' paths with, so the flag is refused by name
    with pytest.raises(ValueError, match=r"^config\.glints: .*" + alg):
        jaxvcm.RenderConfig(algorithm=alg, glints=True)
    assert jaxvcm.RenderConfig(algorithm="vcm", glints=True).record()["glints"] is True
