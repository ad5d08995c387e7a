"""Glossy vertices in every bidirectional technique, per path length, against light tracing
alone: SmallVCM's Cornell box (scenes/_base/cornell_box.toml, no spheres: nothing specular,
so light tracing samples every path) under its point light (scenes/cornell_point.toml's
light), the floor glossy.

Light tracing's technique (k, 1) is the only technique of `lt` for paths of k segments, so
its MIS weight is 1 and its image is an unbiased estimate of the k-segment image L_k by
itself. pt splits it over emitter hits (none: a point light) and NEE (1, k); bdpt splits
L_k over (1, k) NEE, (s, t) connections and (k, 1), vcm adds the merges of photon y_{s-1}
at z_{t-1} (s + t - 2 = k); the weights of each path sum to 1, so their sum estimates the
same L_k. A mistake in a join's pdf at a glossy vertex breaks that sum and nothing else:
each technique alone is still unbiased. For example, with the vertex kind of a medium
scattering event (KIND_MEDIUM) equal to MAT_GLOSSY (3), every glossy vertex is a "medium"
vertex at the joins (no cosine in its area pdfs, the volume kernel in merging), and L_3
comes out 14 % (floor k_d only), 4.5 % (Phong only) and 10 % (both) low in bdpt, while the
unidirectional estimators (pt, lt) stay right and both MIS forms share the error.

The floors: the glossy model with only its Lambertian lobe (k_d 0.8, k_s 0: a test that the
glossy code path equals the diffuse one in the weights) and both lobes (k_d 0.4, k_s 0.4,
exponent 2: a broad lobe, so connections through it matter). The floor's reflectances are
scene arrays, so both floors share one compiled program per algorithm. Statistics: image
means of independent passes; the standard error of the difference must be small enough to
see a 5 % error at 4 standard errors (measured after the fix, 256 passes of 32 spp at 8x8:
SE of L_3 ~0.6 % for lt, ~0.5 % for bdpt, agreement within 1 SE).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig, technique_images
from jaxvcm._io._scene_file import read_scene_doc

from .. import _analytic as A

DEPTH = 3
PASSES = 256
FLOORS = {
    "lambert_lobe": {"type": "glossy", "albedo": [0.8] * 3, "glossy": [0.0] * 3,
                     "exponent": 2.0},
    "both_lobes": {"type": "glossy", "albedo": [0.4] * 3, "glossy": [0.4] * 3,
                   "exponent": 2.0},
}


def _scene(floor):
    doc = read_scene_doc("scenes/_base/cornell_box.toml")
    point = read_scene_doc("scenes/cornell_point.toml")["lights"]
    doc["camera"].update(width=8, height=8)
    doc["materials"]["glossy_floor"] = FLOORS[floor]
    doc["lights"] = point
    return jaxvcm.scene_from_dict(doc, f"cornell_point_{floor}")


def _length(label):
    """Segments of the paths a technique image holds (connections s + t - 1, merges of one
    photon s + t - 2)."""
    return label.s + label.t - (1 if label.kind == "connection" else 2)


@functools.partial(A.long_run_jit, static_argnums=(2,))  # many passes: the optimised program
def _passes(scene, keys, cfg):
    def one(k):
        tech, _ = technique_images(scene, k, cfg, merge_lengths=True)
        per = [jnp.zeros((), tech.images.dtype) for _ in range(DEPTH + 1)]
        for lab, img in tech.items():
            assert lab.kind != "merge" or lab.s >= 2, lab  # merges split by photon
            per[_length(lab)] = per[_length(lab)] + jnp.mean(img)
        return jnp.stack(per)
    return jax.lax.map(one, keys)


@functools.lru_cache(maxsize=None)
def _lengths(floor, alg, seed):
    """Per-pass image means of L_k, k = 0..DEPTH: [PASSES, DEPTH + 1] (float64)."""
    cfg = RenderConfig(algorithm=alg, max_depth=DEPTH, rr_depth=DEPTH + 1, spp=32,
                       radius=0.01)
    keys = jnp.stack([jaxvcm.pass_key(seed, i) for i in range(PASSES)])
    return np.asarray(_passes(_scene(floor), keys, cfg), np.float64)


@pytest.mark.parametrize("alg", ["pt", "bdpt", "vcm"])
@pytest.mark.parametrize("floor", list(FLOORS))
def test_bidirectional_path_lengths_equal_light_tracing_on_glossy(floor, alg):
    ref = _lengths(floor, "lt", 1)
    got = _lengths(floor, alg, 2)
    for k in (2, 3):
        a, b = ref[:, k], got[:, k]
        ma, mb = a.mean(), b.mean()
        se = math.hypot(a.std(ddof=1), b.std(ddof=1)) / math.sqrt(PASSES)
        assert se < 0.0125 * ma, (f"L_{k}: SE of the difference {se / ma:.2%} cannot see a "
                                  f"5 % error at 4 SE")
        assert abs(mb - ma) < 4 * se, (f"{alg} L_{k} = {mb:.5f} vs lt {ma:.5f} "
                                       f"({(mb / ma - 1):+.2%}, {abs(mb - ma) / se:.1f} SE)")
