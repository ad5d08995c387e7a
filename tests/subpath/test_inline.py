"""PT's techniques evaluated inside the camera trace (`jaxvcm._inline`, the route of every
PT pass that wants only its image) against the recorded route (`technique_images`: vertex
records, MIS partial tables, the queued emitter-hit and next-event families).

Same key, same samples: every contribution is computed from the same quantities by the
same functions and the weights by the same operations (`_mis_partial.pt_weight`, checked
against `join` in test_mis_partial.py), so the pass's image must equal the sum of the
technique images to float32 round-off (only the order of the additions differs; measured
<= 4e-8 of the image's largest value), and the passes must count the same camera
vertices. A wrong roulette factor, zero flag, uniform row or MIS partner moves pixels by
far more (a weight that ignored z_{j-1}'s delta flag: several per cent).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._integrator import integrate, pass_stages, technique_images

INLINE_STAGE = "subpaths, emitter hits, next-event estimation"


def test_pt_image_pass_runs_its_techniques_in_the_trace():
    cfg = RenderConfig(algorithm="pt", max_depth=4)
    names = [n for n, _ in pass_stages(cfg, image_only=True)]
    assert names == ["setup", "camera rays", INLINE_STAGE, "film"]
    # technique images, the recursive form and the other algorithms keep the records
    assert INLINE_STAGE not in [n for n, _ in pass_stages(cfg)]
    rec = dataclasses.replace(cfg, mis_form="recursive")
    assert "emitter hits" in [n for n, _ in pass_stages(rec, image_only=True)]
    for alg in ("lt", "bdpt", "ppm", "bpm", "vcm"):
        assert INLINE_STAGE not in [n for n, _ in pass_stages(RenderConfig(algorithm=alg),
                                                              image_only=True)]


# (scene, size): pool_sky at 48x48 = 2304 lanes runs the trace's queue (rounds of 1024
# lanes, the shadow rays queued inside each round), the sky an infinite non-delta light
# (emitter hits and NEE weighted against each other); pool_sun at 16x16 runs the plain
# loop over depths (one round of every lane), the sun a delta light (NEE alone, weight 1)
# seen through the delta water surface. Roulette from depth 2 inside paths of up to 6.
@pytest.mark.parametrize("name,size", [("pool_sky", 48), ("pool_sun", 16)],
                         ids=lambda v: str(v))
def test_inline_pt_equals_the_recorded_techniques(name, size):
    scene = jaxvcm.load_scene(f"scenes/{name}.toml", width=size, height=size)
    cfg = RenderConfig(algorithm="pt", max_depth=6, rr_depth=2)
    key = jax.random.key(11)
    # both routes in one program (one compile)
    (tech, stats_rec), (img, bad, stats) = jax.jit(
        lambda s, k: (technique_images(s, k, cfg), integrate(s, k, cfg)))(scene, key)
    images = {(lab.s, lab.t): np.asarray(v, np.float64) for lab, v in tech.items()}
    assert all(np.all(np.isfinite(v)) for v in images.values())
    total = sum(images.values())
    scale = float(np.max(np.abs(total)))
    # teeth: both technique families contribute
    hits = sum(v.sum() for (s, _), v in images.items() if s == 0)
    nee = sum(v.sum() for (s, _), v in images.items() if s == 1)
    assert nee > 0 and (hits > 0 or name == "pool_sun"), (hits, nee)
    err = float(np.max(np.abs(np.asarray(img, np.float64) - total)))
    assert err <= 1e-5 * scale, f"max |inline - recorded| {err:.3g} of {scale:.3g}"
    assert int(bad) == 0
    assert int(stats.camera_vertices) == int(stats_rec.camera_vertices) > size * size


def test_inline_pt_gradient_equals_the_recorded_route():
    # Same key, same samples: the derivative of the pass w.r.t. the water's coefficients
    # flows through the same estimator weights on both routes (sampling detached), so the
    # inline route's gradient (through the trace's per-lane sums) must equal the recorded
    # route's (through the records and the technique families) to round-off. (Against
    # finite differences, in expectation: test_gradients.py, the same image size.)
    import equinox as eqx
    import jax.numpy as jnp

    scene = jaxvcm.load_scene("scenes/pool_sky.toml", width=48, height=48)
    cfg = RenderConfig(algorithm="pt", max_depth=5, rr_depth=2)
    key = jax.random.key(5)
    sa0 = scene.water.sigma_a
    ss0 = scene.water.sigma_s + jnp.asarray([0.3, 0.2, 0.1], sa0.dtype)
    w = jnp.asarray([1.0, 2.0, 3.0], sa0.dtype)

    def with_water(sa, ss):
        return eqx.tree_at(lambda s: (s.water.sigma_a, s.water.sigma_s), scene, (sa, ss))

    def inline_route(sa, ss):
        return jnp.sum(jnp.mean(integrate(with_water(sa, ss), key, cfg)[0], axis=(0, 1)) * w)

    def recorded_route(sa, ss):
        tech, _ = technique_images(with_water(sa, ss), key, cfg)
        return jnp.sum(jnp.mean(jnp.sum(tech.images, axis=0), axis=(0, 1)) * w)

    g_in, g_rec = jax.jit(lambda sa, ss: (jax.grad(inline_route, argnums=(0, 1))(sa, ss),
                                          jax.grad(recorded_route, argnums=(0, 1))(sa, ss)))(
        sa0, ss0)
    for name, a, b in zip(("sigma_a", "sigma_s"), g_in, g_rec):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        scale = float(np.max(np.abs(b)))
        assert scale > 0 and np.all(np.isfinite(a)), (name, a, b)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * scale, err_msg=name)
