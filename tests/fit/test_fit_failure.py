"""Fits that keep their parameters physical, refuse targets they cannot mean, and say
plainly when they failed.

(a) the bounded map of the solver's variable (`_bounds.Bounds`) and the verdict
    (`_solver.assess`), on the host (no renderer); (b) targets and initial values a fit
    cannot mean are refused before any work, one line naming the field (config: exit 2;
    API: ValueError); (c) two tiny fits (pool_sky at 4x4, PT depth 4, 4 passes, one region
    over the whole image): one forced not to converge, through the CLI (exit 4, fit.json
    "converged": false), one whose target is darker than the scene can show (a coefficient
    at its upper bound, fits badly). The recovery fit that still converges is
    tests/fit/test_fit.py::test_recover_rgb_within_2_percent.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig
from jaxvcm._fit import Region
from jaxvcm._fit._bounds import AT_BOUND, SIGMA_FIT, Bounds, bound_problems, fit_range
from jaxvcm._fit._solver import assess
from jaxvcm.cli import EXIT_FIT_FAILED, main

ROOT = Path(__file__).resolve().parents[2]
POOL_SKY = ROOT / "scenes" / "pool_sky.toml"


# ------------------------------------------------------------------ (a) map and verdict
def test_bounded_map_is_the_identity_inside_and_never_leaves_the_range():
    # SIGMA_FIT in log space: (ln 1e-9, ln 1e6) = (-20.723, 13.816), band 1 (an e-fold)
    b = Bounds.of([SIGMA_FIT] * 2, [True] * 2)
    lo, hi = math.log(1e-9), math.log(1e6)
    np.testing.assert_allclose([b.lo[0], b.hi[0], b.band[0]], [lo, hi, 1.0], rtol=1e-15)
    # inside (lo + 1, hi - 1) x = u exactly: fits that stay there take the unbounded steps
    u = np.array([lo + 1.0, -0.8, 0.0, hi - 1.0])
    bb = Bounds.of([SIGMA_FIT] * 4, [True] * 4)
    assert np.array_equal(bb.to_x_host(u), u) and np.array_equal(bb.to_u(u), u)
    assert np.array_equal(np.asarray(bb.to_x(jnp.asarray(u))), u)
    # far outside, x stays inside [lo, hi] (it reaches a bound only by rounding), and the
    # JAX map is finite in value and in both derivatives there
    for far in (50.0, 1e300):
        x = np.asarray(b.to_x(jnp.asarray([far, -far])))
        assert hi - 1 < x[0] <= hi and lo <= x[1] < lo + 1, x
        assert np.all(np.isfinite(jax.jacfwd(b.to_x)(jnp.asarray([far, -far]))))
        assert np.all(np.isfinite(jax.grad(lambda v: jnp.sum(b.to_x(v)))(
            jnp.asarray([far, -far]))))
    # in a band: the inverse round-trips, and the slope is exp(-(distance into the band)):
    # 2 past hi - 1, x = hi - e^-2 and dx/du = e^-2
    u = np.array([hi + 1.0, lo - 0.5])
    x = b.to_x_host(u)
    np.testing.assert_allclose(x, [hi - math.exp(-2.0), lo + math.exp(-1.5)], rtol=1e-12)
    np.testing.assert_allclose(b.to_u(x), u, rtol=1e-12)
    np.testing.assert_allclose(b.slope(u), [math.exp(-2.0), math.exp(-1.5)], rtol=1e-12)
    J = np.asarray(jax.jacfwd(b.to_x)(jnp.asarray(u)))
    np.testing.assert_allclose(np.diag(J), b.slope(u), rtol=1e-12)
    # value and slope continuous where the band starts (central differences, h = 1e-6)
    for edge in (hi - 1.0, lo + 1.0):
        e = np.array([edge, edge])
        d = (b.to_x_host(e + 1e-6) - b.to_x_host(e - 1e-6)) / 2e-6
        np.testing.assert_allclose(d, 1.0, atol=1e-6)
    # at a bound: slope below AT_BOUND = 0.01, i.e. more than ln(100) = 4.6 into the band
    u = np.array([hi - 1.0 + 4.7, lo + 1.0 - 4.5])
    assert b.slope(u)[0] < AT_BOUND < b.slope(u)[1]
    assert b.side(u).tolist() == [1, 0] and b.side(-np.array([1e300, -1e300])).tolist() == [-1, 1]
    assert bound_problems(["sigma_a[2]", "sigma_s[0]"], [1, -1], [SIGMA_FIT] * 2) == [
        "sigma_a[2] at its upper bound 1e+06 1/m", "sigma_s[0] at its lower bound 1e-09 1/m"]


def test_water_leaf_ranges():
    # log space: 0 raised to 1e-9; linear: a range starting at 0 mirrored below it (a_cdom
    # may cross 0), g's own range kept
    assert fit_range("a_cdom", False).text() == "(1e-09, 1e+06) 1/m"
    assert fit_range("a_cdom", True).text() == "(-1e+06, 1e+06) 1/m"
    assert fit_range("g", True).text() == "(-0.999, 0.999)"
    assert fit_range("S", False).text() == "(1e-09, 0.1) 1/nm"
    assert fit_range("a_400", False) is None  # a subclass's leaf: unbounded
    b = Bounds.of([fit_range("g", True), None], [False, False])
    # linear band: 1 % of the range 1.998; the unbounded leaf is the identity everywhere
    np.testing.assert_allclose(b.band[0], 0.01998, rtol=1e-12)
    assert np.asarray(b.to_x(jnp.asarray([5.0, 1e30]))).tolist() == [0.999, 1e30]
    # 0.006 into the lower band (it starts at -0.999 + 0.01998 = -0.97902): x = -0.999 +
    # 0.01998 exp(-0.006 / 0.01998)
    x = float(b.to_x(jnp.asarray([-0.98502, 0.0]))[0])
    assert x == pytest.approx(-0.999 + 0.01998 * math.exp(-0.006 / 0.01998), abs=1e-12)


def test_verdict_lines():
    names = ["floor", "wall"]
    ok = assess("successful", 12, [0.3, 1.9], names, 2.0, [])
    assert ok == (True, [], "fit converged: max dE2000 1.9 <= 2")
    # not converged after 1 step, both regions beyond 2 (NaN counts as bad), one bound
    c, p, v = assess("nonlinear_max_steps_reached", 1, [20.3, np.nan], names, 2.0,
                     ["sigma_a[2] at its upper bound 1e+06 1/m"])
    assert not c and p[0] == "did not converge: nonlinear_max_steps_reached after 1 step"
    assert p[1].startswith("fits badly: max dE2000 ") and p[1].endswith(
        "> 2 (regions: floor, wall)")
    assert v == "fit " + "; ".join(p) and p[2].startswith("sigma_a[2]")
    c, p, v = assess("successful", 28, [20.3, 0.1], names, 2.0, [])
    assert c and v == "fit converged but fits badly: max dE2000 20.3 > 2 (regions: floor)"


# ------------------------------------------------------------------ (b) refused up front
CONFIG = """
space = "{space}"
[render]
passes = 1
width = 8
height = 8
{extra}
[scenes.pool]
file = "{scene}"
{override}
[[regions]]
name = "floor"
scene = "pool"
rect = [2, 2, 6, 6]
target = {target}
"""

# case -> (space, target, extra tables, scene override, the field the one line names)
REFUSED = {
    "srgb_zero": ("srgb", "[0, 0, 0]", "", "", "regions[0].target"),
    "srgb_one_zero": ("srgb", "[0.1, 0.0, 0.3]", "", "", "regions[0].target"),
    "xyz_negative": ("xyz", "[0.1, -0.01, 0.3]", "", "", "regions[0].target"),
    "nan": ("srgb", "[nan, 0.2, 0.3]", "", "", "regions[0].target[0]"),
    "inf": ("xyz", "[0.1, inf, 0.3]", "", "", "regions[0].target[1]"),
    "lab_black": ("lab", "[0, 10, 10]", "", "", "regions[0].target"),
    "lab_over_white": ("lab", "[120, 0, 0]", "", "", "regions[0].target"),
    "init_above": ("srgb", "[0.1, 0.2, 0.3]", "[init]\nsigma_a = 2e6", "", "init.sigma_a"),
    # the range is open: a start at the bound could never move (u = +inf)
    "init_at_bound": ("srgb", "[0.1, 0.2, 0.3]", "[init]\nsigma_s = [0.1, 0.1, 1e6]", "",
                      "init.sigma_s[2]"),
    "init_below": ("srgb", "[0.1, 0.2, 0.3]", "[init]\nsigma_a = 1e-10", "", "init.sigma_a"),
    # no [init]: the first scene's water is the start, and sigma_s = 0 is outside
    "init_from_scene": ("srgb", "[0.1, 0.2, 0.3]", "", "override = { water = { sigma_s = 0 } }",
                        "init.sigma_s"),
    "max_delta_e_zero": ("srgb", "[0.1, 0.2, 0.3]", "[solver]\nmax_delta_e = 0", "",
                         "solver.max_delta_e"),
}


@pytest.mark.parametrize("case", sorted(REFUSED), ids=sorted(REFUSED))
def test_refused_before_any_work(case, tmp_path, capsys):
    space, target, extra, override, field = REFUSED[case]
    p = tmp_path / f"{case}.toml"
    p.write_text(CONFIG.format(space=space, target=target, extra=extra, override=override,
                               scene=POOL_SKY.as_posix()))
    out = tmp_path / "out"
    rc = main(["fit", str(p), "--out", str(out)])
    _, err = capsys.readouterr()
    lines = err.splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"jaxvcm: error: {p}: {field}: "), lines[0]
    assert not out.exists()  # nothing rendered or written


def test_api_refuses_targets_and_starts():
    # the same checks in jaxvcm.fit / fit_spectral, before anything is traced (no
    # compilation here: the ValueError comes from the argument checks)
    scene = jaxvcm.load_scene(POOL_SKY, width=4, height=4)
    with pytest.raises(ValueError, match=r"^regions\.a\.target: must be > 0 in every"):
        jaxvcm.fit(scene, [Region("a", 0, (0, 0, 4, 4), (0.0, 0.0, 0.0))])
    with pytest.raises(ValueError, match=r"^regions\.a\.target: must be finite"):
        jaxvcm.fit(scene, [Region("a", 0, (0, 0, 4, 4), (math.nan, 0.1, 0.1))], space="xyz")
    with pytest.raises(ValueError, match=r"^regions\.a\.target: L must lie in \(0, 100\]"):
        jaxvcm.fit(scene, [Region("a", 0, (0, 0, 4, 4), (0.0, 0.0, 0.0))], space="lab")
    ok = [Region("a", 0, (0, 0, 4, 4), (0.1, 0.1, 0.1))]
    with pytest.raises(ValueError, match=r"^init\.sigma_a: must lie in \(1e-09, 1e\+06\) 1/m"):
        jaxvcm.fit(scene, ok, init_sigma_a=1e6)
    with pytest.raises(ValueError, match=r"^init\.sigma_s: must lie in"):
        jaxvcm.fit(scene, ok, init_sigma_s=[0.1, math.nan, 0.1])
    sp = jaxvcm.spectral_scene(scene, jaxvcm.WaterModel(b_p=0.1), n_wavelengths=2)
    with pytest.raises(ValueError, match=r"^init\.b_p: must lie in \(1e-09, 1e\+06\) 1/m"):
        jaxvcm.fit_spectral(sp, ok, ["b_p"], init={"b_p": 2e6})
    with pytest.raises(ValueError, match=r"^init\.g: must lie in \(-0\.999, 0\.999\)"):
        jaxvcm.fit_spectral(sp, ok, ["g"], linear=["g"], init={"g": -1.0})


# ------------------------------------------------------------------ (c) tiny fits
# pool_sky at 4x4, PT to depth 4 (camera -> surface -> floor -> surface -> sky: the floor
# is lit), no Russian roulette, 4 passes; one region over the whole image. Its colour runs
# from 0.134 (sigma_a -> 0) down to 0.069 (sigma_a -> infinity: the sky in the surface and
# the walls above the water, which no absorption touches), measured at these keys.
RENDER = dict(algorithm="pt", max_depth=4, rr_depth=100)
WHOLE = (0, 0, 4, 4)


def _config(tmp_path, head: str) -> None:
    """tmp_path / fit.toml: `head` (the [render] and [solver] tables) and one region, the
    whole 4 x 4 image of pool_sky, with target grey 0.1."""
    (tmp_path / "fit.toml").write_text(head + f"""
[scenes.pool]
file = "{POOL_SKY.as_posix()}"
[[regions]]
name = "all"
scene = "pool"
rect = [0, 0, 4, 4]
target = [0.1, 0.1, 0.1]
""")


def test_fit_stopped_early_is_reported_and_exits_4(tmp_path, capsys):
    """max_steps = 1: optimistix's Cauchy termination compares two successive iterates, so
    a single step can never end "successful"; the result is nonlinear_max_steps_reached.
    The target 0.1 is reachable (between 0.069 and 0.134), but the start (the scene's
    sigma_a, colour 0.095 in red, 0.125 / 0.130 in green / blue) is 6.6 dE2000 from it and
    one step moves nothing: "fits badly" too."""
    _config(tmp_path, """
[render]
algorithm = "pt"
max_depth = 4
rr_depth = 100
passes = 4
width = 4
height = 4
[solver]
max_steps = 1
free = "sigma_a"
""")
    out = tmp_path / "out"
    rc = main(["fit", str(tmp_path / "fit.toml"), "--out", str(out), "--quiet"])
    o, err = capsys.readouterr()
    assert rc == EXIT_FIT_FAILED == 4, err
    verdict = ("fit did not converge: nonlinear_max_steps_reached after 1 step; fits badly: "
               "max dE2000 ")
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"jaxvcm: warning: {verdict}"), err
    assert f"\n{verdict}" in o  # the summary says it too
    res = json.loads((out / "fit.json").read_text())
    assert res["converged"] is False and res["result"] == "nonlinear_max_steps_reached"
    assert res["verdict"].startswith(verdict) and res["verdict"].endswith("(regions: all)")
    assert len(res["problems"]) == 2 and res["at_bound"] == {}
    assert res["max_delta_e"] == 2.0 and res["delta_e2000_max"] > 2.0
    assert (out / "fit.png").stat().st_size > 10_000  # the outputs are still written


def test_target_darker_than_the_scene_ends_at_a_bound():
    """Target 0.03, below the 0.069 no absorption can darken: the colour saturates as
    sigma_a grows, d colour / d ln sigma_a -> 0, and the Gauss-Newton step -r / J grows
    without limit (unbounded, this was sigma_a = 1e32 "successful"). Bounded, the first
    step already takes the least absorbed channel, blue (J ~ sigma_a = 0.02 /m, the
    smallest), into the band below 1e6 /m; there J = 0 exactly and the solver stops:
    converged, with a coefficient at its upper bound, and fits badly: dE2000 between the
    greys Y = 0.03 (L* 20.1) and Y ~ 0.069 (L* 31.6) is dL / S_L = 11.5 / 1.36 = 8.5 > 2."""
    scene = jaxvcm.load_scene(POOL_SKY, width=4, height=4)
    res = jaxvcm.fit(scene, [Region("all", 0, WHOLE, (0.03, 0.03, 0.03))],
                     config=RenderConfig(**RENDER), passes=4, free="sigma_a")
    assert res.result == "successful" and res.converged and not res.ok
    assert np.all(res.sigma_a <= 1e6) and np.all(res.sigma_a > 10.0), res.sigma_a
    assert np.all(np.isfinite(res.sigma_a_sd))
    assert res.at_bound and set(res.at_bound.values()) == {"upper"}, res.at_bound
    for name in res.at_bound:
        assert f"{name} at its upper bound 1e+06 1/m" in res.problems
    assert 7.5 < float(res.delta_e2000[0]) < 9.5
    assert res.verdict.startswith("fit converged but fits badly: max dE2000 ")
    d = res.to_dict()
    assert d["converged"] is True and d["at_bound"] == res.at_bound
    assert d["problems"] == res.problems and d["verdict"] == res.verdict
    assert res.summary().splitlines()[-1] == res.verdict


def test_fit_too_large_for_int32_is_refused_before_any_work(tmp_path, capsys):
    # A fit renders each pass in one chunk: PT at depth 6 has D + 1 = 7 index items per
    # path, so one chunk holds at most 2^30 / 7 = 153,391,689 paths, and 16384^2 x 1 spp =
    # 268,435,456 paths cannot be indexed; refused in one line naming the config's fields,
    # before a scene is rendered (it died with RESOURCE_EXHAUSTED after 50 s)
    _config(tmp_path, """
[render]
width = 16384
height = 16384
""")
    rc = main(["fit", str(tmp_path / "fit.toml"), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("jaxvcm: error: render.width, render.height: a fit renders each "
                             "pass in one chunk, and 16384 x 16384 x 1 spp paths are more "
                             "than the 153391689"), err


def test_fit_larger_than_memory_is_refused_once_compiled(monkeypatch):
    # The solver is compiled ahead of time and XLA's memory analysis of it compared with the
    # device's budget before it runs: a budget of 1 kB (no 4x4 fit's program is that small:
    # its arguments alone are the scene) refuses it in one line, nothing run
    from jaxvcm._fit import _model

    monkeypatch.setattr(_model, "device_budget", lambda device: 1024)
    scene = jaxvcm.load_scene(POOL_SKY, width=4, height=4)
    with pytest.raises(ValueError, match=r"^render.width, render.height: the fit's compiled "
                       r"solver at 4 x 4 needs about .* GiB, more than the 9.54e-07 GiB "):
        jaxvcm.fit(scene, [Region("all", 0, WHOLE, (0.1, 0.1, 0.1))],
                   config=RenderConfig(**RENDER), passes=4, free="sigma_a", max_steps=1)
