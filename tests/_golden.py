"""Fixed-key reference renders: the proof that a refactor or a speed change leaves the
renderer's behaviour unchanged.

`cases()` computes a few small renders (PT, BDPT, VCM with both MIS forms, PPM, a spectral
pass with hero dispersion) and one water fit, all through the public API with fixed keys.
`python -m tests._golden` writes them to `tests/data/golden.npz`; `tests/test_golden.py`
recomputes them and compares. They were recorded before the package was re-laid out
(issue: architecture), so every later change must reproduce them or explain why not.
"""

from __future__ import annotations

import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PATH = os.path.join(HERE, "data", "golden.npz")
SIZE = 12  # pixels on a side: every case is compile-bound, the image size barely matters


def _scene(name, **kw):
    import jaxvcm

    return jaxvcm.load_scene(os.path.join(ROOT, "scenes", f"{name}.toml"), width=SIZE,
                             height=SIZE, **kw)


RENDERS = {  # name -> (scene, RenderConfig keywords, pass index)
    "pt_pool": ("pool", dict(algorithm="pt", max_depth=5, rr_depth=2), 0),
    "bdpt_pool": ("pool", dict(algorithm="bdpt", max_depth=4, rr_depth=2), 0),
    "vcm_pool_sun": ("pool_sun", dict(algorithm="vcm", max_depth=4, rr_depth=2), 3),
    "vcm_recursive_pool_sun": ("pool_sun", dict(algorithm="vcm", max_depth=4, rr_depth=2,
                                                mis_form="recursive"), 3),
    "ppm_pool": ("pool", dict(algorithm="ppm", max_depth=4, rr_depth=2, radius=0.05), 1),
}


def render_case(name):
    import jax

    import jaxvcm

    scene_name, kw, index = RENDERS[name]
    img, diag = jax.jit(jaxvcm.render_pass, static_argnums=2)(
        _scene(scene_name), jaxvcm.pass_key(7, index), jaxvcm.RenderConfig(**kw), index)
    assert int(diag.nonfinite) == 0 and not bool(diag.merge_overflow)
    return np.asarray(img)


def spectral_case():
    import jax

    import jaxvcm

    ss = jaxvcm.spectral_scene(_scene("pool"), jaxvcm.WaterModel(pure_scattering=False),
                               n_wavelengths=4, dispersion="hero")
    xyz, _ = jax.jit(jaxvcm.render_pass_spectral, static_argnums=2)(
        ss, jaxvcm.pass_key(3, 0), jaxvcm.RenderConfig(algorithm="pt", max_depth=4,
                                                        rr_depth=2))
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
