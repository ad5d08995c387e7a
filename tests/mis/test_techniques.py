"""`jaxvcm render --techniques`: every technique's image as a layer of the EXR, keyed by
path length and technique, their sum the image that the plain render writes.

The layer set is derived from the algorithm's techniques (vcm, max depth D = 4): the
connections (s, t) with s light and t camera vertices, t >= 1, path length
k = s + t - 1 in 1..D, except s = 0, t = 1 (a camera vertex alone); the merges of photon
y_{s-1} at z_{t-1} for s, t >= 2 with k = s + t - 2 <= D and s - 1 <= D - 1 light
vertices, t - 1 <= D - 1 camera vertices. Their sum equals the plain render's image to
float32 round-off: the same samples, the merges' sums split by photon only.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import jaxvcm
from jaxvcm import RenderConfig, _io
from jaxvcm.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "scenes", "cornell.toml")
D = 4
# radius 0.05 of the view radius: 64 photons a pass, so some merges land (default 0.005:
# none in 2 passes at 8 x 8)
ARGS = ["--width", "8", "--height", "8", "--max-depth", str(D), "--passes", "2",
        "--radius", "0.05", "--quiet"]


def _expected_layers(D):
    conn = {f"k{s + t - 1}_s{s}_t{t}" for t in range(1, D + 2) for s in range(0, D + 1)
            if 1 <= s + t - 1 <= D and (s, t) != (0, 1)}
    merges = {f"k{s + t - 2}_merge_s{s}_t{t}" for s in range(2, D + 1) for t in range(2, D + 1)
              if s + t - 2 <= D}
    return conn | merges


@pytest.fixture(scope="module")
def layered(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("tech") / "cornell.exr")
    rc = main(["render", SCENE, "--techniques", "--out", out] + ARGS)
    assert rc == 0
    return _io.read_exr(out), _io.read_exr_layers(out), out


def test_layers_are_every_technique_by_path_length(layered):
    _, layers, _ = layered
    assert set(layers) == _expected_layers(D)
    # the box is lit: its light seen directly (k = 1; light tracing's (1, 1) carries it,
    # its weight against the emitter hit is about (N / A_light)^2 : (P / Omega_image *
    # cos / d^2)^2 ~ 23^2 : 1 here), direct light by next-event estimation (k = 2) and the
    # merges all put light on the film
    assert layers["k1_s1_t1"].sum() > 0 and layers["k2_s1_t2"].sum() > 0
    assert sum(v.sum() for k, v in layers.items() if "merge" in k) > 0


def test_layers_sum_to_the_image_of_the_plain_render(layered):
    img, layers, _ = layered
    total = sum(v.astype(np.float64) for v in layers.values())
    scale = float(np.abs(img).max())
    assert scale > 0
    np.testing.assert_allclose(total, img, rtol=0, atol=1e-5 * scale)
    scene = jaxvcm.load_scene(SCENE, width=8, height=8)
    plain = jaxvcm.render(scene, "vcm", passes=2, seed=0, progress=False,
                          config=RenderConfig(algorithm="vcm", max_depth=D, radius=0.05))
    np.testing.assert_allclose(img, plain, rtol=0, atol=1e-5 * scale)


@pytest.mark.parametrize("flag", [["--spectral"], ["--resume"], ["--memory", "1G"]],
                         ids=lambda f: f[0].lstrip("-"))
def test_techniques_refuses_what_it_cannot_do(flag, tmp_path, capsys):
    rc = main(["render", SCENE, "--techniques", "--out", str(tmp_path / "x.exr")] + ARGS + flag)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and flag[0] in err[0], err
