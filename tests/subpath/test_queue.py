"""Work queues (`_queue`): compaction changes the work, never the result."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._queue import MIN_ROUND, Packed, first_true, masked_map


@pytest.mark.parametrize("split", [1, 3, 8])
@pytest.mark.parametrize("density", [0.0, 0.07, 1.0])
def test_masked_map_equals_the_dense_map_where_wanted(split, density):
    # 3 x 2000 items (several rounds of MIN_ROUND when split > 1); the kernel sees each
    # wanted item once, with its own arguments, and its result lands in the item's place.
    rng = np.random.default_rng(0)
    shape = (3, 2000)
    mask = jnp.asarray(rng.random(shape) < density)
    a = jnp.asarray(rng.normal(size=shape))
    b = jnp.asarray(rng.integers(0, 100, size=shape + (2,)), jnp.int32)
    fn = lambda x, y: (jnp.sin(x) + y[0].astype(x.dtype), y[1] * 2)  # noqa: E731
    got = jax.jit(lambda m, x, y: masked_map(fn, m, (x, y), (0.0, -1), split))(mask, a, b)
    want = jax.vmap(jax.vmap(fn))(a, b)
    np.testing.assert_array_equal(np.asarray(got[0]), np.where(mask, want[0], 0.0))
    np.testing.assert_array_equal(np.asarray(got[1]), np.where(mask, want[1], -1))


def test_packed_round_trip():
    tree = {"v": (jnp.arange(6.0).reshape(2, 3), jnp.ones((2,))), "k": jnp.array([1, 2]),
            "b": jnp.array([True, False])}
    p = Packed(tree, 1)
    # one array per dtype, one column per scalar field (the [2, 3] leaf: 3 columns)
    assert set(p.arrays) == {str(x.dtype) for x in jax.tree.leaves(tree)}
    assert sum(a.shape[1] for a in p.arrays.values()) == 3 + 1 + 1 + 1
    back = p.unpack(p.arrays)
    for x, y in zip(jax.tree.leaves(back), jax.tree.leaves(tree)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_round_width_does_not_change_the_image():
    # BDPT (depth 3) on the pool at 40x40: 3200 trace lanes, so trace_split 8 runs rounds of
    # MIN_ROUND lanes (a lane's vertices spread over several rounds) and the connection
    # shadow rays several queue rounds; trace_split 1 runs every lane at every
    # step (the plain loop over depths). Each lane sees the same uniforms either way: the same image to float32
    # round-off (XLA may fuse differently for the two widths).
    scene = jaxvcm.load_scene("scenes/pool.toml", width=40, height=40)
    assert 2 * 40 * 40 > 2 * MIN_ROUND
    key = jaxvcm.pass_key(0, 0)
    out = []
    for split in (1, 8):
        cfg = RenderConfig(algorithm="bdpt", max_depth=3).tuned(trace_split=split)
        img, diag = jax.jit(jaxvcm.render_pass, static_argnums=2)(scene, key, cfg)
        out.append((np.asarray(img), int(diag.camera_vertices), int(diag.light_vertices)))
    assert out[0][1:] == out[1][1:]
    assert out[0][0].mean() > 0
    np.testing.assert_allclose(out[0][0], out[1][0], rtol=1e-5, atol=1e-7)


def test_queued_trace_runs_every_step_of_every_lane():
    # A closed furnace (camera inside an emitting sphere of albedo 0.5, no roulette before
    # depth 4): every lane lives for all 4 steps, the worst case for the queued trace.
    # 12 x 12 pixels x 16 spp = 2304 lanes in rounds of W = 1024: the lanes that start last
    # (2304 - 2 x 1024 = 256 of them) need 4 rounds of their own after the 2 x 4 full ones,
    # 12 in all; the trace once ran ceil(4 x 2304 / 1024) = 9 rounds, so lanes 2111.. stopped
    # at depth 2 and the image came out 3.7 % dark (1.8055 against 1 + .5 + .25 + .125 =
    # 1.875). Now the vertex counts equal the plain loop's (trace_split 1) and the image
    # equals it and the closed form. With trace_tail 2 the rounds with at most 512 live
    # lanes run a step 512 wide (`_subpath.tail_width`): here the last 256 lanes' 4 rounds,
    # which must still take every step (the default, 1024 / 8 = 128 < TAIL_MIN: none).
    from jaxvcm._subpath import TAIL_MIN, tail_width
    from .. import _scenes as S
    scene = jaxvcm.scene_from_dict(S.sphere_furnace((1.0, 1.0, 1.0), (0.5, 0.5, 0.5), w=12, h=12))
    key = jaxvcm.pass_key(0, 0)
    out = []
    for split, tail in ((1, 8), (8, 8), (8, 2)):
        cfg = RenderConfig(algorithm="pt", max_depth=4, spp=16).tuned(trace_split=split,
                                                                     trace_tail=tail)
        assert (tail_width(MIN_ROUND, cfg, True) == TAIL_MIN) == (tail == 2)
        img, diag = jax.jit(jaxvcm.render_pass, static_argnums=2)(scene, key, cfg)
        out.append((np.asarray(img, np.float64), int(diag.camera_vertices)))
    assert 12 * 12 * 16 > 2 * MIN_ROUND
    # the default (0, auto): tail rounds W / 8 wide from max_depth 3 rr_depth on
    assert tail_width(8192, RenderConfig(max_depth=12), True) == 1024
    assert tail_width(8192, RenderConfig(max_depth=11), True) is None
    assert tail_width(8192, RenderConfig(max_depth=12), False) is None  # trace_both
    with pytest.raises(ValueError, match="config.trace_tail"):
        RenderConfig().tuned(trace_tail=-1)
    for o in out[1:]:
        assert o[1] == out[0][1] == 12 * 12 * 16 * 4, (out[0][1], o[1])
        np.testing.assert_allclose(o[0], out[0][0], rtol=1e-5, atol=1e-7)
    # NEE and emitter hits in a furnace: every path's value is exactly 1.875 up to MIS
    # noise; the mean of 2304 of them is within 1 %
    assert abs(out[1][0].mean() / 1.875 - 1.0) < 0.01, out[1][0].mean()


@pytest.mark.parametrize("frac", [0.0, 0.6, 1.0])
def test_masked_map_cheap_rounds(frac):
    # 6000 items, rounds of MIN_ROUND: the items `cheap_mask` marks are queued first, and a
    # round made of them alone runs cheap_fn. cheap_fn here returns a tagged value (+1000)
    # so the test sees which kernel each item got: every unmarked item gets fn, a marked
    # item gets cheap_fn unless it shared a round with unmarked ones (at most one round of
    # MIN_ROUND items), and each wanted item lands in its own place once.
    rng = np.random.default_rng(1)
    n = 6000
    mask = jnp.asarray(rng.random(n) < 0.8)
    cm = jnp.asarray(rng.random(n) < frac)
    a = jnp.asarray(rng.normal(size=n))
    fn = lambda x: jnp.sin(x)  # noqa: E731
    cheap = lambda x: jnp.sin(x) + 1000.0  # noqa: E731
    got = np.asarray(jax.jit(lambda m, c, x: masked_map(fn, m, (x,), 0.0, 8, cheap=(cheap, c)))(
        mask, cm, a))
    want = np.sin(np.asarray(a))
    m, c = np.asarray(mask), np.asarray(cm)
    tagged = got > 500
    np.testing.assert_allclose(np.where(tagged, got - 1000.0, got), np.where(m, want, 0.0),
                               rtol=1e-6, atol=1e-6)
    assert not np.any(tagged & ~(m & c)), "cheap_fn ran on an item it is not valid for"
    n_cheap = int(np.sum(m & c))
    W = 6000 // 8 if 6000 // 8 >= MIN_ROUND else MIN_ROUND
    assert int(np.sum(tagged)) >= n_cheap - W, "the marked items did not get cheap rounds"
    if frac == 1.0:
        assert int(np.sum(tagged)) == n_cheap


@pytest.mark.parametrize("density", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("size", [1, 700, 5000])
def test_first_true_equals_nonzero(density, size):
    # `first_true` is jnp.nonzero(m, size=size, fill_value=m.size) by another route (one
    # running count, one scatter): the same indices in the same order, the same padding,
    # and the True items beyond `size` left out, for a size below, near and above the count
    rng = np.random.default_rng(1)
    m = jnp.asarray(rng.random(3000) < density)
    got = jax.jit(first_true, static_argnums=1)(m, size)
    want = jnp.nonzero(m, size=size, fill_value=m.size)[0]
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def _dense_emitter_hits(scene, cfg, cam, verts):
    """Emitter hits at every slot z_j (j = 1..D) of every path, each weighted by the
    full-path oracle: {(0, j + 1): [N, C]}."""
    from jaxvcm import _connect as connect
    from jaxvcm._path import log_n_light_tracing
    from jaxvcm._subpath import rows
    from .._mis_oracle import pdfs, weight
    D = cfg.max_depth
    N = cam.A.shape[1]
    js = np.arange(1, D + 1)
    z, zp = rows(cam, js), rows(cam, js - 1)
    lid = jnp.where(verts.escaped, connect._sky_id(scene), jnp.maximum(verts.light, 0))
    vv = lambda f: jax.vmap(jax.vmap(f))  # noqa: E731
    A_s, A_s1, _, _ = vv(lambda z_, zp_, l, e: connect.emitter_hit_join_pdfs(scene, z_, zp_, l, e))(
        z, zp, lid, verts.escaped)
    P = pdfs(cam)
    one = jnp.ones((), A_s.dtype)
    log_n = log_n_light_tracing(cfg, N, A_s.dtype)

    def w1(j, n):  # technique (0, j + 1) of path n
        lane = jax.tree.map(lambda a: a[:, n], P)
        return weight(cfg, jnp.int32(0), j + 1, lane, lane, A_s[j - 1, n], A_s1[j - 1, n], one,
                      one, jnp.zeros((), bool), verts.escaped[j - 1, n], log_n)

    w = jax.vmap(lambda j: jax.vmap(lambda n: w1(j, n))(jnp.arange(N, dtype=jnp.int32)))(
        jnp.asarray(js, jnp.int32))
    ok = z.alive & jnp.any(verts.Le > 0, axis=-1)
    val = jnp.where(ok[..., None], z.beta * verts.Le * w[..., None], 0.0)
    return {(0, int(j) + 1): val[i] for i, j in enumerate(js)}


def test_queued_emitter_hits_and_lazy_nee_uniforms():
    # PT (depth 4) on the pool under a sky at 48x48: 2304 camera paths, so the emitter-hit
    # queue (rounds of N / 8 = 288 -> MIN_ROUND items over 4 x 2304 slots) runs 9 rounds.
    # (1) The queued emitter hits (weights from the camera partials at the join) equal every
    # (vertex, path) slot evaluated densely with the full-path oracle's weight (the path
    # assembled and weighted by `mis_weight`, tests/_mis_oracle.py): the same contribution
    # per (technique, path) to float32 round-off, and the sky is hit (mean > 0).
    # (2) Next-event estimation hashing each item's uniforms (`Uniforms.at`) equals it
    # reading the dense table: the same numbers (`_uniforms`), so the same values exactly.
    from jaxvcm import _connect as connect, _integrator as integ
    from jaxvcm._uniforms import Uniforms
    scene = jaxvcm.load_scene("scenes/pool_sky.toml", width=48, height=48)
    cfg = RenderConfig(algorithm="pt", max_depth=4)

    @jax.jit
    def run(key):
        st = integ.PassState(key=key, pass_index=0)
        for name, stage in integ.pass_stages(cfg):
            if name in ("emitter hits", "next-event estimation"):
                break
            st = stage(scene, cfg, st)
        q = connect.emitter_hits(scene, cfg, st.cends, st.cverts, st.mis_etas, st.parts)
        d = _dense_emitter_hits(scene, cfg, st.cends, st.cverts)
        u = Uniforms.draw(st.keys[2], (cfg.max_depth - 1, 48 * 48, 3), jnp.float32)
        nl = connect.next_event(scene, cfg, st.cends, u, st.mis_etas, st.parts)
        nd = connect.next_event(scene, cfg, st.cends, u.dense(), st.mis_etas, st.parts)
        return q, d, nl, nd

    q, d, nl, nd = run(jaxvcm.pass_key(0, 0))
    assert set(q) == set(d) == {(0, j) for j in range(2, cfg.max_depth + 2)}
    assert float(sum(jnp.sum(v) for v in q.values())) > 0
    for label in q:
        np.testing.assert_allclose(np.asarray(q[label]), np.asarray(d[label]), rtol=2e-5,
                                   atol=1e-6 * float(jnp.max(d[label]) + 1e-30))
    assert float(sum(jnp.sum(v) for v in nl.values())) > 0
    for label in nl:
        np.testing.assert_array_equal(np.asarray(nl[label]), np.asarray(nd[label]))



@pytest.mark.parametrize("split", [1, 4])
def test_masked_map_summed_per_path(split):
    # 3 x 2000 (technique, path) items, 30 % wanted; split 4 runs rounds of MIN_ROUND. The
    # summed mode adds each wanted item's result into its path's row (the sum over the 3
    # rows of the dense map's output), zeroing and counting its non-finite elements as the
    # film does: items with x > 2.2 return inf in one channel (about 1.4 % of them).
    rng = np.random.default_rng(2)
    shape = (3, 2000)
    mask = jnp.asarray(rng.random(shape) < 0.3)
    x = jnp.asarray(rng.normal(size=shape))
    fn = lambda a: jnp.stack([jnp.sin(a), jnp.where(a > 2.2, jnp.inf, a * a)])  # noqa: E731
    got, bad = jax.jit(lambda m, a: masked_map(fn, m, (a,), 0.0, split, summed=True))(mask, x)
    dense = np.asarray(jax.vmap(jax.vmap(fn))(x), np.float64)  # [3, 2000, 2]
    wanted = np.asarray(mask)[..., None]
    finite = np.isfinite(dense)
    want = np.where(wanted & finite, dense, 0.0).sum(axis=0)
    n_bad = int(np.sum(wanted & ~finite))
    assert n_bad > 0
    assert int(bad) == n_bad
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6, atol=1e-6)
