"""`jaxvcm bench --peer mitsuba` without Mitsuba: one line, exit status 2; and the
Mitsuba scene dict's pure-Python parts (tessellated water with analytic normals, rectangle
transforms, camera, medium, sky). Nothing here needs Mitsuba or compiles a JAX program
(only eager elementwise ops on small arrays)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import jaxvcm
from benchmarks import bench as _bench
from benchmarks import peer_mitsuba as P
from jaxvcm import _scene

from .. import _oracles as O

POOL, SKY = "scenes/pool.toml", "scenes/pool_sky.toml"


@pytest.fixture(scope="module")
def pool():
    return jaxvcm.load_scene(POOL, width=16, height=16)


def test_without_mitsuba_one_line_and_status_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # `import mitsuba` raises ImportError
    out = tmp_path / "bench.md"
    rc = _bench.main(["--peer", "mitsuba", "--out", str(out), "--reference-dir",
                      str(tmp_path / "refs")])
    assert rc == P.EXIT_UNAVAILABLE == 2
    o, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("jaxvcm: bench --peer mitsuba: Mitsuba 3 is not installed")
    assert "libllvm19" in lines[0] and o == ""
    assert not out.exists() and not (tmp_path / "refs").exists()  # nothing measured


def test_peer_usage_errors(capsys):
    assert _bench.main(["--peer", "mitsuba", "--algorithms", "vcm"]) == 2
    assert _bench.main(["--peer-seconds", "3"]) == 2
    assert _bench.main(["--peer", "mitsuba", "--profile"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(ln.startswith("jaxvcm: error: bench:") for ln in err)


def test_kinds_match_the_package():
    assert (P.MAT_DIFFUSE, P.MAT_DIELECTRIC, P.MAT_MIRROR) == (
        _scene.MAT_DIFFUSE, _scene.MAT_DIELECTRIC, _scene.MAT_MIRROR)
    assert (P.LIGHT_RECT, P.LIGHT_SPHERE, P.LIGHT_SUN, P.LIGHT_SKY) == (
        _scene.LIGHT_RECT, _scene.LIGHT_SPHERE, _scene.LIGHT_SUN, _scene.LIGHT_SKY)
    assert (P.PHASE_ISOTROPIC, P.PHASE_HG) == (_scene.PHASE_ISOTROPIC, _scene.PHASE_HG)


def test_water_grid_vertices_normals_and_winding(pool):
    n = 128
    V, N, F = jaxvcm.water_grid(pool, n)
    assert V.shape == N.shape == (n * n, 3) and F.shape == (2 * (n - 1) ** 2, 3)
    assert F.min() == 0 and F.max() == n * n - 1
    fp = np.asarray(pool.water.footprint, np.float64)
    assert np.allclose(V[[0, n * n - 1]][:, [0, 2]], [[fp[0], fp[2]], [fp[1], fp[3]]])
    waves, level = O.waves_of(pool.water), float(pool.water.level)
    h = O.heightfield(waves, level, V[:, 0], V[:, 2])[0]
    nrm = O.heightfield_normal(waves, level, V[:, 0], V[:, 2])
    assert np.allclose(V[:, 1], h, atol=2e-6)  # the scene's float32 heights
    assert np.allclose(N, nrm, atol=2e-5)
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-12)
    # every triangle faces up, and at 128 x 128 its geometric normal is close to the mean
    # of its analytic vertex normals (the tessellation resolves the waves)
    a, b, c = (V[F[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    assert np.all(fn[:, 1] > 0)
    vn = N[F].mean(axis=1)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    assert np.min(np.sum(fn * vn, axis=1)) > 0.999
    with pytest.raises(ValueError):
        jaxvcm.water_grid(pool, 1)


def test_rect_to_world_maps_the_unit_square():
    rng = np.random.default_rng(0)
    p0, e1, e2 = rng.normal(size=(3, 3))
    m = P.rect_to_world(p0, e1, e2)
    for (u, v), want in [((-1, -1), p0), ((1, -1), p0 + e1), ((-1, 1), p0 + e2),
                         ((1, 1), p0 + e1 + e2)]:
        assert np.allclose((m @ [u, v, 0.0, 1.0])[:3], want)
    n = np.cross(e1, e2)
    # Mitsuba transforms normals by the inverse transpose: the rectangle's +z normal
    mn = np.linalg.inv(m[:3, :3]).T @ [0.0, 0.0, 1.0]
    assert np.allclose(mn / np.linalg.norm(mn), n / np.linalg.norm(n))


def _shapes(spec, kind):
    return {k: v for k, v in spec.items() if isinstance(v, dict) and v.get("type") == kind}


def test_scene_spec_of_the_pool(pool):
    spec = P.scene_spec(pool, max_depth=8, rr_depth=4, water_resolution=8)
    assert spec["integrator"] == {"type": "volpath", "max_depth": 8, "rr_depth": 4}
    cam = spec["sensor"]
    assert cam["fov"] == pytest.approx(42.0) and cam["fov_axis"] == "y"
    assert (cam["film"]["width"], cam["film"]["height"]) == (16, 16)
    assert cam["film"]["rfilter"] == {"type": "box"}
    o, t, up = cam["to_world"]["look_at"]
    assert np.allclose(o, [0.0, 3.5, 1.25])
    f = np.array([0.0, -4.7, -1.6])
    assert np.allclose((t - o) / np.linalg.norm(t - o), f / np.linalg.norm(f), atol=1e-6)
    rects = _shapes(spec, "rectangle")
    assert len(rects) == 6  # floor, 4 walls, the light
    light = rects.pop("light_rect_0")
    assert light["emitter"] == {"type": "area", "radiance": {"type": "rgb",
                                                             "value": [1200.0] * 3}}
    m = light["to_world"]
    assert np.allclose(m[:3, 3], [0.25, 3.0, -0.25]) and np.allclose(m[:3, 2], [0, -1, 0])
    assert np.allclose(np.linalg.norm(m[:3, :2], axis=0), 0.075)
    for r in rects.values():  # basin: two-sided diffuse, no emitter
        assert r["bsdf"]["type"] == "twosided" and r["bsdf"]["bsdf"]["type"] == "diffuse"
        assert "emitter" not in r
    floor = [r for r in rects.values() if np.allclose(r["to_world"][:3, 2], [0, 1, 0])]
    assert len(floor) == 1
    assert floor[0]["bsdf"]["bsdf"]["reflectance"]["value"] == pytest.approx([0.85] * 3)
    water = spec["water"]
    assert water["vertices"].shape == (64, 3) and water["faces"].shape == (98, 3)
    assert water["bsdf"] == {"type": "dielectric", "int_ior": pytest.approx(1.33),
                             "ext_ior": 1.0}
    med = water["interior"]
    st = np.array([0.48, 0.10, 0.05])
    assert med["sigma_t"]["value"] == pytest.approx(st)
    assert med["albedo"]["value"] == pytest.approx(0.03 / st)
    assert med["phase"] == {"type": "isotropic"}
    assert not _shapes(spec, "envmap")


def test_scene_spec_sky_is_the_upper_hemisphere():
    scene = jaxvcm.load_scene(SKY, width=8, height=8)
    spec = P.scene_spec(scene, max_depth=4, rr_depth=4, water_resolution=4, sky_rows=16)
    (sky,) = _shapes(spec, "envmap").values()
    bmp = sky["bitmap"]
    assert bmp.shape[0] == 16 and bmp.shape[2] == 3
    assert np.all(bmp[:8] == 1.0) and np.all(bmp[8:] == 0.0)  # row 0 = +y
    assert not any("emitter" in v for v in _shapes(spec, "rectangle").values())
