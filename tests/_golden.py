"""Fixed-key reference renders: the proof that a refactor or a speed change leaves the
renderer's behaviour unchanged.

`cases()` computes a few small renders (PT, BDPT, VCM with both MIS forms, PPM, a spectral
pass with hero dispersion) and one water fit, all through the public API with fixed keys.
`python -m tests._golden` writes them to `tests/data/golden.npz`;
`tests/transport/test_golden.py` recomputes them and compares. Every change to the renderer
must reproduce them or explain why not (`bdpt_pool`, for one, weights its paths through
the water surface with the pdfs after a delta vertex converted to area: the `_subpath`
module doc, "Delta vertices").
"""

from __future__ import annotations

import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PATH = os.path.join(HERE, "data", "golden.npz")
SIZE = 12  # pixels on a side: every case is compile-bound, the image size barely matters


def _scene(name, size=SIZE):
    import jaxvcm

    return jaxvcm.load_scene(os.path.join(ROOT, "scenes", f"{name}.toml"), width=size,
                             height=size)


def _medium_furnace():
    import jaxvcm

    from . import _scenes as S

    return jaxvcm.scene_from_dict(S.medium_furnace(np.array([1.0, 2.0, 0.5]), (0.3, 0.6, 1.2),
                                                   w=8, h=8))


# name -> (scene, RenderConfig keywords, key (seed, pass index), driver). Each case is the
# same compiled program as an assertion test elsewhere in the suite (named in the comment),
# so the persistent compilation cache serves both and this check costs the suite little.
RENDERS = {
    # tests/geometry/test_hard_cases.py::test_render_pass_vmaps_over_keys_and_jits
    "pt_pool": (lambda: _scene("pool", 8), dict(algorithm="pt", max_depth=3), (7, 0), "jit"),
    # tests/transport/test_bidir.py::test_technique_images_sum_to_the_bdpt_image
    "bdpt_pool": (lambda: _scene("pool", 12), dict(algorithm="bdpt", max_depth=5), (7, 1),
                  "jit"),
    # tests/merge/test_merge.py::test_merging_extreme_radii_are_finite[0.5-vcm] / [0.5-ppm]
    "vcm_pool_sun": (lambda: _scene("pool_sun", 8), dict(algorithm="vcm", max_depth=4,
                                                         radius=0.5), (7, 3), "host"),
    "ppm_pool_sun": (lambda: _scene("pool_sun", 8), dict(algorithm="ppm", max_depth=4,
                                                         radius=0.5), (7, 2), "host"),
    # tests/mis/test_mis_recursive.py::test_recursive_render_equals_explicit[vcm]
    "vcm_medium_furnace": (_medium_furnace, dict(algorithm="vcm", max_depth=3, radius=0.1),
                           (5, 0), "host"),
    "vcm_recursive_medium_furnace": (_medium_furnace, dict(algorithm="vcm", max_depth=3,
                                                           radius=0.1, mis_form="recursive"),
                                     (5, 0), "host"),
}


def render_case(name):
    import jax

    import jaxvcm

    make, kw, (seed, index), driver = RENDERS[name]
    scene, cfg, key = make(), jaxvcm.RenderConfig(**kw), jaxvcm.pass_key(seed, index)
    if driver == "jit":  # called as those tests call it: pass index 0 (a constant)
        img, diag = jax.jit(jaxvcm.render_pass, static_argnums=2)(scene, key, cfg)
    else:
        img, diag, _ = jaxvcm.render_pass_host(scene, key, cfg, index)
    assert int(diag.nonfinite) == 0 and not bool(diag.merge_overflow)
    return np.asarray(img)


def spectral_case():
    import jax

    import jaxvcm

    ss = jaxvcm.spectral_scene(_scene("pool", 8), jaxvcm.WaterModel(pure_scattering=False),
                               n_wavelengths=4, dispersion="hero")
    xyz, _ = jax.jit(jaxvcm.render_pass_spectral, static_argnums=2)(
        ss, jaxvcm.pass_key(3, 0), jaxvcm.RenderConfig(algorithm="pt", max_depth=3))
    return np.asarray(xyz)


def fit_case():
    """A two-region RGB fit of sigma_a (sigma_s fixed) on pool_sky, 2 passes, 4 steps."""
    import jaxvcm

    scene = _scene("pool_sky")
    regions = [jaxvcm.Region("floor", 0, (3, 4, 9, 9), (0.085, 0.170, 0.195)),
               jaxvcm.Region("near", 0, (3, 9, 9, 12), (0.118, 0.132, 0.133))]
    res = jaxvcm.fit(scene, regions, passes=2, seed=1, free="sigma_a", max_steps=6,
                     config=jaxvcm.RenderConfig(algorithm="pt", max_depth=4, rr_depth=2))
    assert res.iterations >= 2
    return np.concatenate([res.sigma_a, res.sigma_s, np.ravel(res.fitted)]).astype(np.float64)


def cases():
    out = {name: render_case(name) for name in RENDERS}
    out["spectral_hero_pool"] = spectral_case()
    out["fit_pool_sky"] = fit_case()
    return out


if __name__ == "__main__":
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_dtype_promotion", "strict")
    values = cases()
    np.savez_compressed(PATH, **values)
    for k, v in values.items():
        print(k, v.shape, v.dtype, float(np.mean(v)))
