"""The hash grid's `precise` condition at the user boundary: a merging radius too
small for the scene's float dtype at the scene's extent is a one-line error naming
config.radius before any pass runs (`_merge.check_precise`, called by every host driver
through `_render.with_retry`), never a silent miss of neighbours; a float64 scene resolves
it. pool_sun's box spans 8.2 m (|coordinate| + extent): in float32 the grid resolves cells
down to 8.2 m / (2^-7 / (32 x 2^-24) - 2) = 2.0 mm, i.e. radii >= 0.99 mm, a first-pass
fraction 3.56e-4 of the bounding radius.
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


def _ok(scene, cfg, i=0):
    try:
        _merge.check_precise(scene, cfg, i)
        return True
    except ValueError:
        return False


def test_check_equals_the_grids_own_flag(sun):
    # points at the corners of the scene's box (the largest span any pass can have): the
    # host check and the float32 grid's traced `precise` flag agree on both sides of the
    # threshold (3.56e-4 of the bounding radius)
    lo, hi = np.asarray(sun.bounds)
    pts = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                    for c in (lo[2], hi[2])], np.float32)
    rb = 0.5 * float(np.linalg.norm(hi - lo))
    seen = set()
    for r in (1e-5, 3.4e-4, 3.55e-4, 3.57e-4, 3.6e-4, 5e-3):
        g = _hashgrid.build(*(jnp.asarray(pts[:, k]) for k in range(3)), None, r * rb,
                            table_size=16, dtype=jnp.float32)
        ok = _ok(sun, RenderConfig(algorithm="vcm", radius=r))
        assert ok == bool(g.precise), (r, ok, bool(g.precise))
        seen.add(ok)
    assert seen == {True, False}


def test_too_small_a_radius_is_a_one_line_error(sun):
    cfg = RenderConfig(algorithm="vcm", max_depth=4, radius=1e-6)
    with pytest.raises(ValueError, match=r"^config\.radius: pass 1's merging radius .* float32"):
        render_pass_host(sun, jax.random.key(0), cfg, 0)
    # ... a float64 scene resolves it; algorithms without merging have nothing to check
    sun64 = jaxvcm.load_scene("scenes/pool_sun.toml", width=8, height=8, dtype=jnp.float64)
    assert _ok(sun64, cfg)
    assert _ok(sun, RenderConfig(algorithm="bdpt", radius=1e-6))


def test_a_later_pass_that_shrinks_below_it_is_refused(sun):
    # alpha 0.1: r_i = r_1 i^(-0.3) (the grid's radius, the medium's schedule), so a first
    # radius of 4e-4 (above 3.56e-4) is 0.81 of itself at pass 2: refused there
    cfg = RenderConfig(algorithm="ppm", radius=4e-4, alpha=0.1)
    assert _ok(sun, cfg, 0)
    with pytest.raises(ValueError, match=r"config\.radius: pass 2's"):
        _merge.check_precise(sun, cfg, 1)


def test_cli_refuses_it_in_one_line(tmp_path, capsys):
    rc = main(["render", "scenes/pool_sun.toml", "--radius", "1e-6", "--passes", "1",
               "--width", "8", "--height", "8", "--out", str(tmp_path / "x.exr"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "config.radius" in err[0], err


@pytest.mark.parametrize("alg", ["ppm", "vcm"])
def test_the_flag_is_in_the_diagnostics_under_a_users_jit(sun, alg):
    # A user's own jit has no host check: the grid's traced flag comes back in
    # Diagnostics.merge_imprecise. One program (the radius schedule is traced through the
    # pass index): alpha 0.1 gives r_i = r_1 i^(-0.3), so r_1 = 4e-4 (above the 3.56e-4
    # threshold) is r_1 x 10^4^-0.3 = 2.5e-5 at pass 10^4, 14x below it at any photon
    # extent of at least 1/14 of the box's
    cfg = RenderConfig(algorithm=alg, max_depth=3, radius=4e-4, alpha=0.1)
    f = jax.jit(jaxvcm.render_pass, static_argnums=2)
    _, ok = f(sun, jax.random.key(0), cfg, 0)
    _, bad = f(sun, jax.random.key(0), cfg, 9999)
    assert not bool(ok.merge_imprecise) and bool(bad.merge_imprecise)
    assert _ok(sun, cfg, 0) and not _ok(sun, cfg, 9999)  # the host check agrees
