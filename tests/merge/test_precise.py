"""The merging radius's floor: the hash grid resolves a radius only down to a limit set by
the scene's float dtype and extent (`_hashgrid.build`'s `precise` condition); the radius
schedule stops there (`_merge.pass_radius`) and the render goes on, with one warning line
(`_merge.radius_floor_note`), never a silent miss of neighbours and never an error that
ends a progressive render. pool_sun's box (its shapes and water, [-1, -1.2, -1] ..
[1, 0.3, 1]) spans 3 m (|coordinate| + extent, along x and z): in float32 the grid resolves
cells down to 3 m / (2^-7 / (32 x 2^-24) - 2) = 0.733 mm, i.e. radii >= 0.364 mm, a
first-pass fraction 2.27e-4 of the bounding radius
(1.60 m, half the box's diagonal sqrt(2^2 + 1.5^2 + 2^2)); the floor is 1 % above it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm import _hashgrid, _merge
from jaxvcm._render import render_pass_host
from jaxvcm.cli import main


@pytest.fixture(scope="module")
def sun():
    return jaxvcm.load_scene("scenes/pool_sun.toml", width=8, height=8)


def test_the_floor_is_the_grids_own_limit(sun):
    # points at the corners of the scene's box (the largest span any pass can have): the
    # float32 grid's traced `precise` flag holds exactly down to the host's limit
    # (2.27e-4 of the bounding radius), and the traced limit equals the host's
    lo, hi = np.asarray(sun.bounds)
    pts = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                    for c in (lo[2], hi[2])], np.float32)
    rb = 0.5 * float(np.linalg.norm(hi - lo))
    r_min, _ = _merge.precise_radius(sun)
    assert np.isclose(r_min / rb, 2.271e-4, rtol=2e-3)
    np.testing.assert_allclose(float(_merge.resolvable_radius(sun)), r_min, rtol=1e-5)
    for r in (1e-5, 2.2e-4, 2.265e-4, 2.277e-4, 2.3e-4, 5e-3):
        g = _hashgrid.build(*(jnp.asarray(pts[:, k]) for k in range(3)), None, r * rb,
                            table_size=16, dtype=jnp.float32)
        assert bool(g.precise) == (r * rb > r_min), (r, bool(g.precise))


def test_too_small_a_radius_stays_at_the_floor(sun):
    # a first radius 227x below the limit: the pass runs at the floor (1.01 x the limit),
    # the grid resolves it, and the render's note says so from the first pass
    cfg = RenderConfig(algorithm="vcm", max_depth=4, radius=1e-6)
    r_min, _ = _merge.precise_radius(sun)
    rad = _merge.pass_radius(cfg, sun, 0)
    np.testing.assert_allclose([float(rad.surface), float(rad.medium)],
                               _merge.FLOOR_MARGIN * r_min, rtol=1e-5)
    img, diag, _ = render_pass_host(sun, jax.random.key(0), cfg, 0)
    assert not bool(diag.merge_imprecise) and int(diag.nonfinite) == 0
    assert np.all(np.isfinite(np.asarray(img)))
    note = _merge.radius_floor_note(sun, cfg, 1)
    assert note.startswith("config.radius: the merging radius stayed at ") and (
        "from the first pass" in note and "float32" in note), note
    # ... a float64 scene resolves it; algorithms without merging have no radius
    sun64 = jaxvcm.load_scene("scenes/pool_sun.toml", width=8, height=8, dtype=jnp.float64)
    assert _merge.radius_floor_note(sun64, cfg, 1) is None
    assert _merge.radius_floor_note(sun, RenderConfig(algorithm="bdpt", radius=1e-6), 1) is None


def test_a_schedule_that_reaches_it_stays_there(sun):
    # alpha 0.1: the surface radius r_1 i^(-0.45), the medium's r_1 i^(-0.3); r_1 = 2.6e-4
    # (above the 2.294e-4 floor) reaches it at pass 2 on surfaces (0.73 of itself: 1.90e-4)
    # and in the medium (0.81: 2.11e-4): from then on both stay at the floor, never below
    cfg = RenderConfig(algorithm="ppm", radius=2.6e-4, alpha=0.1)
    r_min, _ = _merge.precise_radius(sun)
    floor = _merge.FLOOR_MARGIN * r_min
    assert _merge.radius_floor_note(sun, cfg, 1) is None
    assert "from pass 2:" in _merge.radius_floor_note(sun, cfg, 9)
    first = _merge.pass_radius(cfg, sun, 0)
    assert float(first.surface) > floor and float(first.medium) > floor
    for i in (1, 10, 9999):
        rad = _merge.pass_radius(cfg, sun, i)
        np.testing.assert_allclose([float(rad.surface), float(rad.medium)], floor, rtol=1e-5)


def test_cli_renders_on_with_one_warning_line(tmp_path, capsys):
    rc = main(["render", "scenes/pool_sun.toml", "--radius", "1e-6", "--passes", "2",
               "--width", "8", "--height", "8", "--max-depth", "4", "--out",
               str(tmp_path / "x.exr"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 0 and len(err) == 1, err
    assert err[0].startswith("jaxvcm: warning: config.radius: the merging radius stayed at")
    assert "from the first pass" in err[0]


@pytest.mark.parametrize("alg", ["ppm", "vcm"])
def test_no_imprecise_pass_under_a_users_jit(sun, alg):
    # A user's own jit has no host driver: the floor is in the traced pass itself. One
    # program (the radius schedule is traced through the pass index): alpha 0.1 gives
    # r_i = r_1 i^(-0.3), so r_1 = 4e-4 would be 2.5e-5 at pass 10^4, 9x below the grid's
    # limit; the grid's flag stays down there and the images stay finite
    cfg = RenderConfig(algorithm=alg, max_depth=3, radius=4e-4, alpha=0.1)
    f = jax.jit(jaxvcm.render_pass, static_argnums=2)
    for i in (0, 9999):
        img, d = f(sun, jax.random.key(0), cfg, i)
        assert not bool(d.merge_imprecise) and int(d.nonfinite) == 0, i
        assert np.all(np.isfinite(np.asarray(img)))
