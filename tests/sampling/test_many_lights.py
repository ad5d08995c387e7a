"""Scenes that scale: lights evaluated once per group of one kind, waves in a rolled loop.

Every per-light evaluation (`_lights.groups`) runs one code copy per (kind, aim) group on
the parameters of the light at hand, and the waves' sums run in `_geometry.over_waves`'
rolled loop: the compiled program must not grow with the number of lights or waves (a
scene with 200 lights or 1,000 waves compiled for minutes at gigabytes when each was
unrolled). The oracles: the program's size (lowered, not compiled: cheap), and every light
of a mixed scene sampled, emitted and weighed exactly as in a scene that holds it alone,
its pdfs times its selection probability.
"""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm import _lights as L
from jaxvcm import _vec as vec
from jaxvcm._render import render_pass

from .. import _scenes as S


def _pool(n_lights: int = 1, n_waves: int | None = None) -> dict:
    """The shipped pool at 8x8: its one rect light split into `n_lights` (a row of lights
    of the same size along x, radiance shared), and `n_waves` waves (the shipped four
    repeated, amplitudes scaled so the surface's slope bound stays that of the pool)."""
    d = S.shipped_doc("pool", 8, 8)
    l0 = d["lights"][0]
    d["lights"] = []
    for i in range(n_lights):
        li = copy.deepcopy(l0)
        li["center"] = [l0["center"][0] + 0.2 * i, l0["center"][1], l0["center"][2]]
        li["radiance"] = l0["radiance"] / n_lights
        d["lights"].append(li)
    if n_waves is not None:
        w0 = d["water"]["waves"]
        d["water"]["waves"] = [[w0[i % 4][0] * 4 / n_waves] + list(w0[i % 4][1:3])
                               + [w0[i % 4][3] + 0.1 * i] for i in range(n_waves)]
    return d


def _program_lines(doc: dict, algorithm: str) -> int:
    scene = jaxvcm.scene_from_dict(doc)
    cfg = RenderConfig(algorithm=algorithm, max_depth=4)
    low = jax.jit(render_pass, static_argnums=2).lower(scene, jaxvcm.pass_key(0, 0), cfg)
    return low.as_text().count("\n")


@pytest.mark.parametrize("algorithm", ["bdpt"])
def test_program_does_not_grow_with_lights_or_waves(algorithm):
    # The program of 2 lights vs 24, and of 8 waves vs 48. Unrolled, each light added
    # ~600 StableHLO lines to a VCM program and each wave ~660 (measured), so 22 more
    # lights or 40 more waves would add > 13,000 lines; grouped and rolled, the count
    # changes only by the constant tables' text (the lights' kind table): allow 1 %. Four
    # waves (the shipped pools) are one trip of the loop's four-wave body, which XLA gets
    # without the loop: a few hundred lines fewer (3 % allowed).
    two = _program_lines(_pool(2), algorithm)
    many = _program_lines(_pool(24), algorithm)
    assert abs(many - two) <= 0.01 * two, (two, many)
    eight = _program_lines(_pool(1, 8), algorithm)
    many_w = _program_lines(_pool(1, 48), algorithm)
    assert abs(many_w - eight) <= 0.01 * eight, (eight, many_w)
    four = _program_lines(_pool(1, 4), algorithm)
    assert abs(many_w - four) <= 0.03 * four, (four, many_w)


def _mixed() -> dict:
    """Lights of every kind a connection reads, two of some kinds (groups of one and of
    two members), in the pool. The scene's box (the sun's disk, the lights' selection by
    power) is its surfaces', lights' rects and spheres included: a small diffuse rect at
    the box's top corner keeps the box the same whichever lights a scene holds."""
    d = S.shipped_doc("pool", 8, 8)
    d["shapes"].append({"type": "rect", "center": [0.9, 3.1, 0.9], "normal": [0.0, -1.0, 0.0],
                        "size": [0.1, 0.1], "material": "wall"})
    rect = d["lights"][0]
    rect2 = copy.deepcopy(rect)
    rect2.update(center=[-0.4, 2.5, 0.3], size=[0.3, 0.1], radiance=[300.0, 200.0, 100.0])
    d["lights"] = [
        rect,
        {"type": "sphere", "center": [0.5, 2.0, 0.4], "radius": 0.1, "radiance": 50.0},
        {"type": "point", "position": [-0.3, 2.2, -0.2], "intensity": [4.0, 3.0, 2.0]},
        rect2,
        {"type": "sphere", "center": [-0.6, 1.8, -0.5], "radius": 0.2,
         "radiance": [10.0, 20.0, 30.0]},
        {"type": "point", "position": [0.2, 2.8, 0.6], "intensity": 7.0},
        {"type": "sun", "direction": [-0.25, -1.0, 0.2], "irradiance": 3.0},
    ]
    return d


def test_each_light_of_many_behaves_as_alone():
    d = _mixed()
    many = jaxvcm.scene_from_dict(d)
    sel = np.asarray(L.selection_pdf(many))
    groups = L.groups(many)
    # rect, sphere, point: two members each; the sun alone
    assert sorted(len(g.members) for g in groups) == [1, 2, 2, 2]
    rng = np.random.default_rng(3)
    p = vec.Vec3(*(jnp.asarray(v, jnp.float32) for v in (0.1, -0.5, 0.05)))  # the floor
    u = jnp.asarray(rng.uniform(size=(16, 5)), jnp.float32)
    cdf = np.concatenate([[0.0], np.cumsum(sel)])

    @jax.jit
    def evaluate(scene, u_sel, u):
        s = L.sample_light(scene, p, u_sel, u[1], u[2])
        e = L.sample_emission(scene, u.at[0].set(u_sel))
        Le, pdf = L.emitted_surface(scene, s.light, -s.wi, s.n, s.dist)
        pt = L.light_point_pdf(scene, e.light, -e.d)
        pd = L.emission_pdf_dir(scene, e.light, e.n, e.d, e.p)
        to = L.emitted_toward(scene, e.light, e.d, e.n)
        return s, e, Le, pdf, pt, pd, to

    for i in range(len(d["lights"])):
        alone = jaxvcm.scene_from_dict({**d, "lights": [d["lights"][i]]})
        np.testing.assert_array_equal(np.asarray(alone.bounds), np.asarray(many.bounds))
        mid = 0.5 * (cdf[i] + cdf[i + 1])  # picks light i in the mixed scene
        for uu in u[:4]:
            sm, em, Lem, pm, ptm, pdm, tom = evaluate(many, jnp.float32(mid), uu)
            sa, ea, Lea, pa, pta, pda, toa = evaluate(alone, jnp.float32(0.5), uu)
            assert int(sm.light) == i and int(em.light) == i
            close = dict(rtol=2e-5, atol=1e-7)
            for a, b in ((sm.wi, sa.wi), (sm.n, sa.n), (em.p, ea.p), (em.d, ea.d),
                         (em.o, ea.o)):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), **close)
            np.testing.assert_allclose(sm.dist, sa.dist, **close)
            np.testing.assert_allclose(sm.Le, sa.Le, **close)
            np.testing.assert_allclose(Lem, Lea, **close)
            np.testing.assert_allclose(tom, toa, **close)
            np.testing.assert_allclose(pdm, pda, **close)  # direction pdf: no selection
            # the selection probability is in every light pdf: the mixed scene's pdfs are
            # the lone light's (selection 1) times sel_i (a delta light's "pdf" is its
            # selection probability alone)
            np.testing.assert_allclose(sm.pdf_w, sa.pdf_w * sel[i], **close)
            np.testing.assert_allclose(pm, pa * sel[i], **close)
            np.testing.assert_allclose(ptm, pta * sel[i], **close)
            np.testing.assert_allclose(em.pdf_pos, ea.pdf_pos * sel[i], **close)
            np.testing.assert_allclose(em.beta1, ea.beta1 / sel[i], **close)
    # no light (-1, a vertex that is not on one) is in no group: its pdfs are 0, as they
    # were when each light compared its own index (without the sun the last light is a
    # point light of a two-member group, which index -1 would wrap to)
    no_sun = jaxvcm.scene_from_dict({**d, "lights": d["lights"][:6]})
    up = vec.Vec3(*(jnp.asarray(v, jnp.float32) for v in (0.0, 1.0, 0.0)))
    none = jnp.int32(-1)
    for sc in (many, no_sun):
        assert float(L.light_point_pdf(sc, none, up)) == 0.0
        assert float(L.emission_pdf_dir(sc, none, up, -up, p)) == 0.0
        Le, pdf = L.emitted_surface(sc, none, up, -up, jnp.float32(1.0))
        assert float(pdf) == 0.0 and not np.any(np.asarray(Le))
